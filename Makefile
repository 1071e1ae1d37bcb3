# Entry points, each self-installing on a fresh machine with only Python 3.11:
#   make up     set everything up, then run the main job (`hammer up`, default cn3 HAMMER, loopback)
#   make test   set everything up, then run the whole test suite (CI's command)
#   make check  the fast tier of the suite (no process started, no training to a threshold, no installs)
# torch is installed first and pinned to the CPU wheel (2.13.0); the project's range admits it,
# so pip never resolves a multi-GB CUDA build.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: setup up test check bench lint clean paper paper-report paper-dose paper-warehouse paper-warehouse-5m paper-warehouse-10m snapshot status faults-ownobs messages edge-chain
# A literal comma for arguments inside $(if ...).
, := ,

# The editable install is strict: a static tree of links to the checkout (build/__editable__.*/hammer/...,
# pyproject's package-dir laid out) on sys.path, not an import hook, so a folder named `hammer` in the
# current folder (the clone itself, seen from the folder that holds it) cannot shadow it, and editors
# follow `hammer.*`. hammer/__init__.py takes the parts from the checkout's folders, so an edit or a new
# module is found at once; $(LINKS) makes the tree again (for editors) when a package folder's entries change.
STRICT := --config-settings editable_mode=strict
LINKS := $(VENV)/.linked
PKG_DIRS := $(patsubst %/__init__.py,%,$(wildcard */__init__.py */*/__init__.py))

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[train,dev,cluster,view]' $(STRICT)
	touch $(STAMP)

$(LINKS): $(STAMP) $(PKG_DIRS)
	$(PY) -m pip install -q --no-deps -e . $(STRICT)
	touch $(LINKS)

setup: $(LINKS)

up: $(LINKS)
	$(VENV)/bin/hammer up $(ARGS)

# The suite on $(JOBS) xdist workers (three: a third fills the cores the others' tests leave idle
# while they wait on clocks and links); tests/conftest.py keeps a module's tests on one worker (its
# fixtures are built once) and names what else must share one. JOBS=0 runs it in this process.
JOBS ?= 3
XDIST = $(if $(filter 0,$(JOBS)),,-n $(JOBS) --dist loadgroup --no-loadscope-reorder)
# Two pytest runs at once: the tests judged on time (mark `serial`, tests/tiers.py) one at a time,
# beside the rest on the workers, which run at the lowest CPU priority (nice 19) so that a serial
# test's processes get a core whenever they want one and the workers only the cycles they leave (most
# serial tests wait on clocks and links). The serial run's output follows the workers'; the 20 slowest
# tests of each close it. Exit status 5 is "none selected" (e.g. ARGS="-k codec").
test: $(LINKS)
	@serial=$$(mktemp); \
	$(PY) -m pytest -q -m serial -p no:cacheprovider --durations=20 $(ARGS) > $$serial 2>&1 & pid=$$!; \
	nice -n 19 $(PY) -m pytest -q -m "not serial" $(XDIST) --durations=20 $(ARGS); workers=$$?; \
	wait $$pid; alone=$$?; \
	echo "== the tests judged on time (mark serial), run beside the workers at a higher priority =="; \
	cat $$serial; rm -f $$serial; \
	[ $$workers -eq 0 -o $$workers -eq 5 ] && [ $$alone -eq 0 -o $$alone -eq 5 ]

# The development loop's default: the tests without a tier mark (tests/tiers.py).
check: $(LINKS)
	$(PY) -m pytest -q --fast $(XDIST) $(ARGS)

bench: $(LINKS)
	$(VENV)/bin/hammer bench $(ARGS)

# The paper's comparisons (docs/results/): resumable, re-run to continue; hours of CPU in total.
# Every finished run is archived under docs/results/runs/ (commit it): archived runs are skipped,
# so the sweeps continue from a fresh clone; reports read the archive.
H := $(VENV)/bin/hammer
A := docs/results/runs
VARIANTS := hammer-rl,hammer-backprop,il,random,centralized
# The grids, each as its sweep arguments (one place for `paper`, `snapshot` and `status`).
G_CN3_MSGLEN := --out runs/paper/cn3-msglen --archive $(A)/cn3-msglen --presets cn3 --variants hammer-rl --seeds 0-2 --grid msg_dim=1,2,4,8
G_CN5 := --out runs/paper/cn5 --archive $(A)/cn5 --presets cn5 --variants $(VARIANTS) --seeds 0-4
G_MW3_PILOT := --out runs/paper/mw3-pilot --archive $(A)/mw3-pilot --presets mw3 --variants hammer-rl,il --seeds 0-2 --episodes 2000
G_CN3 := --out runs/paper/cn3 --archive $(A)/cn3 --presets cn3 --variants $(VARIANTS) --seeds 0-4
G_MW3 := --out runs/paper/mw3 --archive $(A)/mw3 --presets mw3 --variants hammer-rl,il --seeds 0-4
G_MW5_PILOT := --out runs/paper/mw5-pilot --archive $(A)/mw5-pilot --presets mw5 --variants hammer-rl,il --seeds 0-2 --episodes 2000
# cn3 with the authors' PPO settings (Monte-Carlo returns, local lr 1e-4, full-batch epochs).
G_CN3_PAPERPPO := --out runs/paper/cn3-paperppo --archive $(A)/cn3-paperppo --presets cn3 --variants hammer-rl,il --seeds 0-4 --grid gae_lambda=1.0 --grid lr_local=1e-4 --grid minibatches=1
# cn3 where a local agent does not observe the other agents (the central agent still sees everyone);
# random messages as the control for "the message carries information".
G_CN3_OWNOBS := --out runs/paper/cn3-ownobs --archive $(A)/cn3-ownobs --presets cn3 --variants hammer-rl,hammer-backprop,il,random,centralized --seeds 0-4 --grid env_kwargs.observe_others=false
# Its replication on five new seeds, archived and reported on its own.
G_CN3_OWNOBS_REP := --out runs/paper/cn3-ownobs-rep --archive $(A)/cn3-ownobs-rep --presets cn3 --variants hammer-rl,il --seeds 5-9 --grid env_kwargs.observe_others=false
# The dose-response study (docs/results/plan-dose-response.md, declared before its runs): local agents
# see only what lies within obs_radius; 300 runs, so its own target, not part of `paper`.
DOSE_VARIANTS := hammer-rl,hammer-backprop,il,random,centralized
# $(call G_CN3_DOSE,VARIANTS): the grid for some variants (all of them without an argument). Every run with
# compile=true (the plan's amendment of 2026-12-03, before any run: 2.4x faster here).
G_CN3_DOSE = --out runs/paper/cn3-dose --archive $(A)/cn3-dose --presets cn3 --variants $(or $(1),$(DOSE_VARIANTS)) --seeds 0-9 --grid compile=true --grid env_kwargs.obs_radius=1.5,1.0,0.6,0.3,0.0
G_CN3_DOSE_FULL = --out runs/paper/cn3-dose-full --archive $(A)/cn3-dose-full --presets cn3 --variants $(or $(1),$(DOSE_VARIANTS)) --seeds 0-9 --grid compile=true
# The warehouse pilot (docs/results/plan-warehouse.md, step 2): hammer-rl vs IL, 3 seeds, tiny with 2 and 4
# robots. Budget deviation, stated in docs/results/warehouse.md: 1M env steps (2,000 episodes) per run,
# not the plan's B = 5M (10,000), which this shared machine could not give in the session that started it.
G_RWARE_PILOT := --out runs/paper/rware-pilot --archive $(A)/rware-pilot --presets rware-tiny-2ag,rware-tiny-4ag --variants hammer-rl,il --seeds 0-2 --episodes 2000
# Step 3, the comparison (plan-warehouse.md, addendum of 2026-12-03): N = 2 at the pilot's 1M env steps,
# 10 seeds; seeds 0-2 of hammer rl and IL are the pilot's runs (copied into this archive).
# $(call G_RWARE_CMP,VARIANTS,SEEDS)
G_RWARE_CMP = --out runs/paper/rware-cmp --archive $(A)/rware-cmp --presets rware-tiny-2ag --variants $(or $(1),hammer-rl$(,)il$(,)hammer-backprop$(,)random) --seeds $(or $(2),0-9) --episodes 2000
# The same at N = 4 (addendum of 2026-12-03 13:45: both variants learned in the 4-robot pilot).
G_RWARE_CMP4 = --out runs/paper/rware-cmp4 --archive $(A)/rware-cmp4 --presets rware-tiny-4ag --variants $(or $(1),hammer-rl$(,)il$(,)hammer-backprop$(,)random) --seeds $(or $(2),0-9) --episodes 2000
# The primary contrast (hammer-rl vs IL) first at every level, so a grid cut short still answers H1/H2.
paper-dose: $(LINKS)
	$(H) sweep $(call G_CN3_DOSE_FULL,hammer-rl$(,)il) --snapshot-every 20
	$(H) sweep $(call G_CN3_DOSE,hammer-rl$(,)il) --snapshot-every 20
	$(H) sweep $(call G_CN3_DOSE_FULL) --snapshot-every 20
	$(H) sweep $(call G_CN3_DOSE) --snapshot-every 20
	$(MAKE) paper-report
# The warehouse study at its planned budget (docs/results/plan-warehouse.md, addendum): 5M env steps.
G_RW5M_2 := --out runs/paper/rware5m-2 --archive $(A)/rware5m-2 --presets rware-tiny-2ag --episodes 10000
G_RW5M_4 := --out runs/paper/rware5m-4 --archive $(A)/rware5m-4 --presets rware-tiny-4ag --episodes 10000
# Both N at 10M env steps (20,000 episodes): each 5M pilot was still rising (addenda of 2026-12-06 15:13
# for N = 2, 20:05 for N = 4).
G_RW10M_2 := --out runs/paper/rware10m-2 --archive $(A)/rware10m-2 --presets rware-tiny-2ag --episodes 20000
G_RW10M_4 := --out runs/paper/rware10m-4 --archive $(A)/rware10m-4 --presets rware-tiny-4ag --episodes 20000
# Every variant and seed of a warehouse family: what `snapshot` and `status` look at.
RW_ALL := --variants hammer-rl,il,hammer-backprop,random --seeds 0-9
paper-warehouse: $(LINKS)
	$(H) sweep $(G_RWARE_PILOT) --snapshot-every 20
	$(H) sweep $(call G_RWARE_CMP,hammer-rl$(,)il,3-9) --snapshot-every 20
	$(H) sweep $(call G_RWARE_CMP) --snapshot-every 20
	$(H) sweep $(call G_RWARE_CMP4,hammer-rl$(,)il,3-9) --snapshot-every 20
	$(H) sweep $(call G_RWARE_CMP4) --snapshot-every 20
	$(MAKE) paper-report
# Every grid is complete in the archive (2026-12-02): on a clone this skips them all and redraws.
paper: $(LINKS)
	$(H) sweep $(G_CN3_MSGLEN)
	$(H) sweep $(G_CN5)
	$(H) sweep $(G_MW3_PILOT)
	$(H) sweep $(G_CN3)
	$(H) sweep $(G_CN3_PAPERPPO)
	$(H) sweep $(G_CN3_OWNOBS)
	$(H) sweep $(G_CN3_OWNOBS_REP)
	$(H) sweep $(G_MW3)
	$(H) sweep $(G_MW5_PILOT)
	$(MAKE) paper-report

# The pilots (3 seeds of hammer-rl and IL at each N, archived): the plan's rule on them doubled B at both N
# (plan-warehouse.md, addenda of 2026-12-06 15:13 and 20:05), so the grid runs at 10M in
# `make paper-warehouse-10m`; on a clone this skips the archived pilots.
paper-warehouse-5m: $(LINKS)
	$(H) sweep $(G_RW5M_2) --variants hammer-rl,il --seeds 0-2 --snapshot-every 20
	$(H) sweep $(G_RW5M_4) --variants hammer-rl,il --seeds 0-2 --snapshot-every 20

# The study at 10M (plan-warehouse.md, addenda of 2026-12-06), in the plan's order, N = 2 before N = 4 at
# each stage: the 5M pilot runs continued from their last checkpoint to 20,000 episodes (committed in
# $(A)/rware10m-N/_partial/, so a fresh clone restores and resumes them; on the machine that ran a pilot,
# --extend-from finds them in its sweep directory too), then hammer rl and IL seeds 3-9, then all four variants.
paper-warehouse-10m: $(LINKS)
	$(H) sweep $(G_RW10M_2) --variants hammer-rl,il --seeds 0-2 --extend-from runs/paper/rware5m-2 --snapshot-every 20
	$(H) sweep $(G_RW10M_4) --variants hammer-rl,il --seeds 0-2 --extend-from runs/paper/rware5m-4 --snapshot-every 20
	$(H) sweep $(G_RW10M_2) --variants hammer-rl,il --seeds 3-9 --snapshot-every 20
	$(H) sweep $(G_RW10M_4) --variants hammer-rl,il --seeds 3-9 --snapshot-every 20
	$(H) sweep $(G_RW10M_2) $(RW_ALL) --snapshot-every 20
	$(H) sweep $(G_RW10M_4) $(RW_ALL) --snapshot-every 20

# Before a session stops: copy every unfinished run of the paper grids (latest checkpoint, config,
# gzipped metrics) to $(A)/<grid>/_partial/ and commit it; `make paper` on a fresh clone restores
# and resumes those runs. Safe while `make paper` is running. mw3 (4-5 h a run) first.
snapshot: $(LINKS)
	$(H) sweep $(G_MW3) --snapshot
	$(H) sweep $(G_MW5_PILOT) --snapshot
	$(H) sweep $(G_MW3_PILOT) --snapshot
	$(H) sweep $(G_CN5) --snapshot
	$(H) sweep $(G_CN3) --snapshot
	$(H) sweep $(G_CN3_PAPERPPO) --snapshot
	$(H) sweep $(G_CN3_OWNOBS) --snapshot
	$(H) sweep $(G_CN3_OWNOBS_REP) --snapshot
	$(H) sweep $(G_CN3_MSGLEN) --snapshot
	$(H) sweep $(call G_CN3_DOSE_FULL) --snapshot
	$(H) sweep $(call G_CN3_DOSE) --snapshot
	$(H) sweep $(G_RWARE_PILOT) --snapshot
	$(H) sweep $(call G_RWARE_CMP) --snapshot
	$(H) sweep $(call G_RWARE_CMP4) --snapshot
	$(H) sweep $(G_RW5M_2) --variants hammer-rl,il --seeds 0-2 --snapshot
	$(H) sweep $(G_RW5M_4) $(RW_ALL) --snapshot
	$(H) sweep $(G_RW10M_2) $(RW_ALL) --snapshot
	$(H) sweep $(G_RW10M_4) $(RW_ALL) --snapshot

# Where every grid stands (archived, running, resumable, snapshot, not started); changes nothing.
status: $(LINKS)
	@$(H) sweep $(G_MW3) --status
	@$(H) sweep $(G_MW5_PILOT) --status
	@$(H) sweep $(G_MW3_PILOT) --status
	@$(H) sweep $(G_CN5) --status
	@$(H) sweep $(G_CN3) --status
	@$(H) sweep $(G_CN3_PAPERPPO) --status
	@$(H) sweep $(G_CN3_OWNOBS) --status
	@$(H) sweep $(G_CN3_OWNOBS_REP) --status
	@$(H) sweep $(G_CN3_MSGLEN) --status
	@$(H) sweep $(call G_CN3_DOSE_FULL) --status
	@$(H) sweep $(call G_CN3_DOSE) --status
	@$(H) sweep $(G_RWARE_PILOT) --status
	@$(H) sweep $(call G_RWARE_CMP) --status
	@$(H) sweep $(call G_RWARE_CMP4) --status
	@$(H) sweep $(G_RW5M_2) --variants hammer-rl,il --seeds 0-2 --status
	@$(H) sweep $(G_RW5M_4) $(RW_ALL) --status
	@$(H) sweep $(G_RW10M_2) $(RW_ALL) --status
	@$(H) sweep $(G_RW10M_4) $(RW_ALL) --status

# The re-analysis of every published comparison as one family (docs/results/plan-reanalysis.md):
# msglen's m=4 seeds are the cn3 grid's own runs, so only m=1, 2, 8 join.
REANALYSIS_CN = $(A)/cn3 $(wildcard $(A)/cn3-msglen/*msg_dim=1-s*) $(wildcard $(A)/cn3-msglen/*msg_dim=2-s*) \
	$(wildcard $(A)/cn3-msglen/*msg_dim=8-s*) $(A)/cn5 $(A)/cn3-paperppo $(A)/cn3-ownobs $(A)/cn3-ownobs-rep
REANALYSIS = $(REANALYSIS_CN) $(A)/mw3 $(A)/mw3-pilot $(A)/mw5-pilot
paper-report: $(LINKS)
	-$(H) plot $(A)/cn3 --out docs/results/cn3-curves
	-$(H) report $(A)/cn3 --out docs/results/cn3-table.md --export docs/results/cn3-runs.json
	-$(H) plot $(A)/cn3-msglen --window 2000 --out docs/results/cn3-msglen-curves
	-$(H) report $(A)/cn3-msglen --out docs/results/cn3-msglen-table.md --export docs/results/cn3-msglen-runs.json
	-$(H) plot $(A)/cn5 --out docs/results/cn5-curves
	-$(H) report $(A)/cn5 --out docs/results/cn5-table.md --export docs/results/cn5-runs.json
	-$(H) plot $(A)/cn3-paperppo --out docs/results/cn3-paperppo-curves
	-$(H) report $(A)/cn3-paperppo --out docs/results/cn3-paperppo-table.md --export docs/results/cn3-paperppo-runs.json
	-$(H) plot $(A)/cn3-ownobs --out docs/results/cn3-ownobs-curves
	-$(H) report $(A)/cn3-ownobs --out docs/results/cn3-ownobs-table.md --export docs/results/cn3-ownobs-runs.json
	-$(H) report $(A)/cn3-ownobs-rep --out docs/results/cn3-ownobs-rep-table.md --export docs/results/cn3-ownobs-rep-runs.json
	-$(H) plot $(A)/mw3-pilot --out docs/results/mw3-pilot-curves
	-$(H) report $(A)/mw3-pilot --out docs/results/mw3-pilot-table.md --export docs/results/mw3-pilot-runs.json
	-$(H) plot $(A)/mw3 --out docs/results/mw3-curves
	-$(H) report $(A)/mw3 --out docs/results/mw3-table.md --export docs/results/mw3-runs.json
	-$(H) report $(A)/mw3 --best-window 500 --out docs/results/mw3-table-best.md
	-$(H) diagnose $(A)/mw3 --out docs/results/mw3-diagnostics --table docs/results/mw3-diagnostics.md
	-$(H) plot $(A)/mw5-pilot --out docs/results/mw5-pilot-curves
	-$(H) report $(A)/mw5-pilot --out docs/results/mw5-pilot-table.md --export docs/results/mw5-pilot-runs.json
	-$(H) plot $(A)/cn3-ownobs $(A)/cn3-ownobs-rep --band iqm --out docs/results/cn3-ownobs-all-iqm-curves
	-$(H) report $(REANALYSIS) --plan docs/results/plan-reanalysis.md --out docs/results/reanalysis-table.md
	-$(H) report $(REANALYSIS_CN) --auc 10000 --comparisons hammer-rl:il --out docs/results/reanalysis-auc-table.md
	$(if $(wildcard $(A)/cn3-dose),-$(H) report $(A)/cn3-dose $(A)/cn3-dose-full --plan docs/results/plan-dose-response.md --out docs/results/cn3-dose-table.md)
	$(if $(wildcard $(A)/cn3-dose),-$(H) report $(A)/cn3-dose $(A)/cn3-dose-full --auc 10000 --comparisons hammer-rl:il$(,)hammer-backprop:il --out docs/results/cn3-dose-auc-table.md)
	$(if $(wildcard $(A)/cn3-dose),-$(H) dose $(A)/cn3-dose $(A)/cn3-dose-full --out docs/results/cn3-dose-delta --learned-h docs/results/cn3-dose-hidden-learned.md)
	$(if $(wildcard $(A)/cn3-dose),-$(H) plot $(A)/cn3-dose $(A)/cn3-dose-full --band iqm --out docs/results/cn3-dose-curves)
	$(if $(wildcard $(A)/rware-pilot),-$(PY) -m hammer.experiments.rware_pilot $(A)/rware-pilot --floor-json docs/results/warehouse-random-floor.json --out docs/results/warehouse-pilot-table.md)
	$(if $(wildcard $(A)/rware-pilot/*/summary.json),-$(H) plot $(A)/rware-pilot --out docs/results/warehouse-pilot-curves)
	$(if $(wildcard $(A)/$(RWARE_STILLS)/final),-$(H) export $(A)/$(RWARE_STILLS) --out runs/bundles/rware-stills --force && $(H) play runs/bundles/rware-stills --out docs/results/warehouse-team.png --episodes 1 --max-steps 80)
	$(if $(call FAMILY_DONE,rware-cmp),-$(H) report $(A)/rware-cmp --last 200 --comparisons hammer-rl:il$(,)hammer-backprop:il$(,)random:il --digits 3 --out docs/results/warehouse-cmp-table.md)
	$(if $(call FAMILY_DONE,rware-cmp),-$(H) report $(A)/rware-cmp --auc 2000 --comparisons hammer-rl:il$(,)hammer-backprop:il$(,)random:il --digits 3 --out docs/results/warehouse-cmp-auc-table.md)
	$(if $(call FAMILY_DONE,rware-cmp),-$(H) plot $(A)/rware-cmp --band iqm --out docs/results/warehouse-cmp-curves)
	$(if $(call FAMILY_DONE,rware-cmp4),-$(H) report $(A)/rware-cmp4 --last 200 --comparisons hammer-rl:il$(,)hammer-backprop:il$(,)random:il --digits 3 --out docs/results/warehouse-cmp4-table.md)
	$(if $(call FAMILY_DONE,rware-cmp4),-$(H) report $(A)/rware-cmp4 --auc 2000 --comparisons hammer-rl:il$(,)hammer-backprop:il$(,)random:il --digits 3 --out docs/results/warehouse-cmp4-auc-table.md)
	$(if $(call FAMILY_DONE,rware-cmp4),-$(H) plot $(A)/rware-cmp4 --band iqm --out docs/results/warehouse-cmp4-curves)
	$(if $(filter 6,$(words $(wildcard $(A)/rware5m-2/*/summary.json))),-$(H) plot $(A)/rware5m-2 --out docs/results/warehouse5m-2-pilot-curves)
	$(if $(filter 6,$(words $(RW5M_4_PILOT))),-$(H) plot $(RW5M_4_PILOT) --out docs/results/warehouse5m-4-pilot-curves)
	$(if $(call FAMILY_DONE,rware10m-2),-$(H) report $(A)/rware10m-2 --last 2000 --comparisons $(RW_CMP) --digits 3 --out docs/results/warehouse10m-2-table.md)
	$(if $(call FAMILY_DONE,rware10m-2),-$(H) report $(A)/rware10m-2 --auc 20000 --comparisons $(RW_CMP) --digits 3 --out docs/results/warehouse10m-2-auc-table.md)
	$(if $(call FAMILY_DONE,rware10m-2),-$(H) plot $(A)/rware10m-2 --band iqm --out docs/results/warehouse10m-2-curves)
	$(if $(call FAMILY_DONE,rware10m-4),-$(H) report $(A)/rware10m-4 --last 2000 --comparisons $(RW_CMP) --digits 3 --out docs/results/warehouse10m-4-table.md)
	$(if $(call FAMILY_DONE,rware10m-4),-$(H) report $(A)/rware10m-4 --auc 20000 --comparisons $(RW_CMP) --digits 3 --out docs/results/warehouse10m-4-auc-table.md)
	$(if $(call FAMILY_DONE,rware10m-4),-$(H) plot $(A)/rware10m-4 --band iqm --out docs/results/warehouse10m-4-curves)
	-$(MAKE) --no-print-directory messages

# Still frames of a trained 4-robot team (the pilot's hammer rl seed 1) with its messages: warehouse-team.png.
RWARE_STILLS := rware-pilot/rware-tiny-4ag-hammer-rl-ep2000-s1
# A warehouse family (plan-warehouse.md, step 3) is analysed only once all its 40 runs are archived.
FAMILY_DONE = $(filter 40,$(words $(wildcard $(A)/$(1)/*/summary.json)))
# Its three comparisons (Holm across them); the archived runs of N = 4's pilot at 5M (hammer rl, IL, seeds 0-2),
# whose curves are drawn once all six are there.
RW_CMP := hammer-rl:il$(,)hammer-backprop:il$(,)random:il
RW5M_4_PILOT = $(wildcard $(foreach v,hammer-rl il,$(foreach s,0 1 2,$(A)/rware5m-4/rware-tiny-4ag-$(v)-ep10000-s$(s))))
# The warehouse teams' messages (plan-messages.md, addendum of 2026-12-03), one family per N.
WAREHOUSE_MESSAGES = $(H) messages $(A)/$(1) --teams hammer-rl$(,)hammer-backprop$(,)random --episodes 64 --jobs 2 --out docs/results/messages-$(2) --figure docs/results/messages-episode-$(2).png

# What the messages say (docs/results/plan-messages.md): ridge probes and per-agent message cuts of every
# archived hammer / random team with final/ weights (cn3 everything-visible has none archived: skipped, said
# so). Each team's result is kept in the JSON beside its table, so a re-run recomputes only teams whose
# weights changed (the times are in docs/results/README.md). The dose-grid table is
# the plan's whole family (Holm across every setting x target), cn3-ownobs included.
MESSAGE_RUNS := $(A)/cn3-ownobs $(A)/cn3-ownobs-rep $(A)/cn3
messages: $(LINKS)
	$(H) messages $(MESSAGE_RUNS) --out docs/results/messages-cn3-ownobs --figure docs/results/messages-episode.png
	$(if $(wildcard $(A)/cn3-dose),$(H) messages $(MESSAGE_RUNS) $(A)/cn3-dose $(A)/cn3-dose-full --teams hammer-rl$(,)random --out docs/results/messages --figure docs/results/messages-episode-dose.png)
	$(if $(call FAMILY_DONE,rware-cmp),$(call WAREHOUSE_MESSAGES,rware-cmp,warehouse2))
	$(if $(call FAMILY_DONE,rware-cmp4),$(call WAREHOUSE_MESSAGES,rware-cmp4,warehouse4))
	$(if $(call FAMILY_DONE,rware10m-2),$(call WAREHOUSE_MESSAGES,rware10m-2,warehouse10m-2))
	$(if $(call FAMILY_DONE,rware10m-4),$(call WAREHOUSE_MESSAGES,rware10m-4,warehouse10m-4))

# The cn3-ownobs teams (archived with their weights) under the real runtime: hammer with its messages
# and with every message cut, IL without faults; 10 training seeds (backprop mode: 5) x 2 eval seeds
# x 500 episodes.
# $(call TEAMS,label,variant,grid,seeds): label-sN=<archived run of that variant and seed> for each seed.
TEAMS = $(foreach s,$(4),$(1)-s$(s)=$(A)/$(3)/cn3-$(2)-env_kwargs_observe_others=false-s$(s))
OWN_TEAMS = $(call TEAMS,$(1),$(2),cn3-ownobs,0 1 2 3 4) $(call TEAMS,$(1),$(2),cn3-ownobs-rep,5 6 7 8 9)
FAULTS_EVAL := --delays-ms 0 --seeds 2 --episodes 500 --parallel 1
# Ctrl-C stops it (what finished is written); `make faults-ownobs` again continues where it stopped.
faults-ownobs: $(LINKS)
	$(H) faults sweep $(call OWN_TEAMS,hammer,hammer-rl) --drops 0,1.0 $(FAULTS_EVAL) --out runs/faults-ownobs/hammer
	$(H) faults sweep $(call OWN_TEAMS,il,il) --drops 0 $(FAULTS_EVAL) --out runs/faults-ownobs/il
	$(H) faults sweep $(call TEAMS,backprop,hammer-backprop,cn3-ownobs,0 1 2 3 4) --drops 0,1.0 $(FAULTS_EVAL) --out runs/faults-ownobs/hammer-backprop
	for d in hammer hammer-backprop il; do mkdir -p docs/results/faults-ownobs/$$d && cp runs/faults-ownobs/$$d/sweep.csv runs/faults-ownobs/$$d/sweep.md runs/faults-ownobs/$$d/sweep.png docs/results/faults-ownobs/$$d/; done
	$(PY) docs/results/faults_ownobs.py

# The edge chain on this machine (root: network namespaces): the archived trained cn3 team exported,
# served with its central agent and each edge agent (a torch-free venv) in namespaces of their own,
# a hot update and a rollback through the CLI, then `hammer play`; then the archived trained warehouse team
# (rware-tiny-2ag hammer rl s0, 5M env steps) as a secure fleet with its site feed from a namespace of its own
# (publishing the warehouse's current columns), robots on the edge venv, robot 0's link and the feed's link cut
# and restored; figures in runs/edge-chain/chain.json.
# ARGS='--train-episodes 3000' trains both teams with `hammer train` first; ARGS='--rates 0,1024,256' per link rate;
# ARGS='--warehouse RUN' another trained warehouse team, '--warehouse-episodes N' one trained N episodes, '--no-warehouse' none.
edge-chain: $(LINKS)
	$(PY) -m tests.harness.edge_chain $(ARGS)

lint: $(LINKS)
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) build *.egg-info
