"""Tables and the figure of the message analysis (docs/results/plan-messages.md), from the per-team
results of `experiments.messages.analyse_team`.

The comparisons are the plan's: per setting and target (H_agents, H_landmark), the hammer-rl teams'
probe gain against the random-message teams' of the same setting and message length (Welch p, IQM
difference with a bootstrap CI, P(A > B) with a CI), Holm across every (setting x target) pair
present in the results given; the control target V and every other team kind are reported, never
tested. Cut drops: the per-agent drop's mean over teams with a 95 % percentile-bootstrap CI over
teams (`experiments.stats`, fixed seed).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from hammer.experiments.messages import FEATURES, PLAN_TARGETS, TARGETS, TESTED
from hammer.experiments.stats import holm, iqm_ci, iqm_difference_ci, poi_ci, stratified_bootstrap_ci, welch_p

ALPHA = 0.05
# Probes beside the plan's, reported and never tested with it: the rl central policy's noise-free mean,
# and the central agent as initialised (before training) in the same recorded states.
EXPLORATORY = (("probes_mean", "mean message"), ("probes_initial", "untrained central agent"))


def groups(results: list[dict]) -> dict[str, dict[str, list[dict]]]:
    """setting -> label -> team results, teams sorted by training seed."""
    out: dict[str, dict[str, list[dict]]] = {}
    for r in sorted(results, key=lambda r: (r["setting"], r["label"], r["seed"])):
        out.setdefault(r["setting"], {}).setdefault(r["label"], []).append(r)
    return out


def gains(teams: list[dict], target: str, key: str = "probes") -> np.ndarray:
    """The teams' gains on a target; a team where the target is never defined (e.g. a radius that
    never hides the landmark to take: NaN) is left out, so n in the tables counts teams with one."""
    g = raw_gains(teams, target, key)
    return g[np.isfinite(g)]


def raw_gains(teams: list[dict], target: str, key: str = "probes") -> np.ndarray:
    """Every team's gain on a target, NaN where it is undefined (kept: paired comparisons need them)."""
    return np.array([t[key][target]["gain"] for t in teams], dtype=np.float64)


def present(results: list[dict], names: tuple[str, ...]) -> list[str]:
    """The targets among `names` that these teams' task defines (cn: H_landmark, rware: H_shelf), in order."""
    return [n for n in names if any(n in r["probes"] for r in results)]


def iqm_ci_or_nan(g: np.ndarray) -> tuple[float, float, float]:
    """`iqm_ci`, or NaNs (printed as dashes) when no team defines the target."""
    return iqm_ci(g) if len(g) else (float("nan"),) * 3


@dataclass
class Comparison:
    setting: str
    target: str
    a: str
    b: str
    n_a: int
    n_b: int
    mean_a: float
    mean_b: float
    iqm_diff: tuple[float, float, float]
    poi: tuple[float, float, float]
    p: float | None
    p_holm: float | None = None

    @property
    def holds(self) -> bool:
        return self.p_holm is not None and self.p_holm < ALPHA and self.mean_a > self.mean_b


def pairs(labels: list[str]) -> list[tuple[str, str]]:
    """(hammer-rl-mM, random-mM) for every message length M with both."""
    return [(a, "random-" + a.split("-")[-1]) for a in labels
            if a.startswith("hammer-rl-") and "random-" + a.split("-")[-1] in labels]


def comparisons(results: list[dict]) -> list[Comparison]:
    """The plan's tests, Holm-corrected across every one made here."""
    comps = []
    for setting, by_label in groups(results).items():
        for a, b in pairs(list(by_label)):
            for target in present(by_label[a] + by_label[b], TESTED):
                x, y = gains(by_label[a], target), gains(by_label[b], target)
                if not len(x) or not len(y):  # the target is never hidden at this setting: no comparison made
                    continue
                comps.append(Comparison(setting, target, a, b, len(x), len(y), float(x.mean()), float(y.mean()),
                                        iqm_difference_ci(x, y), poi_ci(x, y), welch_p(x, y)))
    ok = [c for c in comps if c.p is not None]
    for c, p in zip(ok, holm([c.p for c in ok]), strict=True):
        c.p_holm = p
    return comps


def mean_ci(x: np.ndarray) -> tuple[float, float, float]:
    """(mean, 95 % percentile-bootstrap CI) over teams."""
    x = np.asarray(x, dtype=np.float64)
    if len(x) < 2:
        return float(x.mean()), float("nan"), float("nan")
    lo, hi = stratified_bootstrap_ci(lambda t: t[0].mean(axis=1), [x])
    return float(x.mean()), lo, hi


def _f(v: float, d: int = 3) -> str:
    return "–" if v is None or not np.isfinite(v) else f"{v:+.{d}f}".replace("-", "−")


def _p(v: float | None) -> str:
    return "–" if v is None else f"{v:.2g}"


def _ci(t: tuple[float, float, float], d: int = 3) -> str:
    return f"{_f(t[0], d)} [{_f(t[1], d)}, {_f(t[2], d)}]"


# ----- markdown -----------------------------------------------------------------------------------
def probe_table(results: list[dict]) -> list[str]:
    """Held-out R² of each feature set and the gain, per setting, team kind and target."""
    lines = ["| setting | teams | n | target | R²[u] | R²[o] | R²[o,u] | gain mean ± s.e. | gain IQM [95 % CI] |",
             "|---|---|---|---|---|---|---|---|---|"]
    for setting, by_label in groups(results).items():
        for label, teams in by_label.items():
            kinds = [("probes", label)] + [(key, f"{label} ({what}, exploratory)") for key, what in EXPLORATORY
                                           if all(key in t for t in teams)]
            for key, name in kinds:
                for target in present(teams, PLAN_TARGETS):
                    g = gains(teams, target, key)
                    r2s = [np.nanmean([t[key][target][f] for t in teams]) if len(g) else np.nan for f in FEATURES]
                    se = g.std(ddof=1) / np.sqrt(len(g)) if len(g) > 1 else float("nan")
                    lines.append(f"| {setting} | {name} | {len(g)} | {target} | " + " | ".join(_f(v) for v in r2s)
                                 + f" | {_f(g.mean() if len(g) else np.nan)} ± {_f(se).lstrip('+')} | "
                                   f"{_ci(iqm_ci_or_nan(g))} |")
    return lines


def comparison_table(comps: list[Comparison]) -> list[str]:
    lines = [("| setting | target | A vs B | n | gain A | gain B | IQM(A) − IQM(B) [95 % CI] | P(A > B) [95 % CI] "
             "| Welch p | Holm p | the messages carry it |"), "|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in comps:
        lines.append(f"| {c.setting} | {c.target} | {c.a} vs {c.b} | {c.n_a} vs {c.n_b} | {_f(c.mean_a)} | "
                     f"{_f(c.mean_b)} | {_ci(c.iqm_diff)} | {c.poi[0]:.2f} [{c.poi[1]:.2f}, {c.poi[2]:.2f}] | "
                     f"{_p(c.p)} | {_p(c.p_holm)} | {'**holds**' if c.holds else 'does not hold'} |")
    return lines


def control_table(results: list[dict]) -> list[str]:
    """The control target V: what a probe finds when the receiver sees the quantity itself."""
    lines = ["| setting | teams | n | V gain mean | V gain IQM [95 % CI] | vs random: Welch p (uncorrected) |",
             "|---|---|---|---|---|---|"]
    for setting, by_label in groups(results).items():
        for label, teams in by_label.items():
            g = gains(teams, "V")
            rnd = by_label.get("random-" + label.split("-")[-1])
            p = welch_p(g, gains(rnd, "V")) if rnd and not label.startswith("random") else None
            lines.append(f"| {setting} | {label} | {len(g)} | {_f(g.mean() if len(g) else np.nan)} | "
                         f"{_ci(iqm_ci_or_nan(g))} | {_p(p)} |")
    return lines


def exploratory_target_table(results: list[dict]) -> list[str]:
    """X_actions, a target the plan did not declare: reported, never tested."""
    lines = ["| setting | teams | n | R²[u] | R²[o] | gain mean | gain IQM [95 % CI] |", "|---|---|---|---|---|---|---|"]
    for setting, by_label in groups(results).items():
        for label, teams in by_label.items():
            if all("X_actions" in t["probes"] for t in teams):
                g = gains(teams, "X_actions")
                r2u, r2o = (np.mean([t["probes"]["X_actions"][f] for t in teams]) for f in ("u", "o"))
                lines.append(f"| {setting} | {label} | {len(g)} | {_f(r2u)} | {_f(r2o)} | "
                             f"{_f(g.mean() if len(g) else np.nan)} | {_ci(iqm_ci_or_nan(g))} |")
    return lines


def initial_table(results: list[dict]) -> list[str]:
    """Exploratory: the trained central agent's gain minus its untrained self's in the same states,
    paired per team (mean, bootstrap CI over teams, paired t-test p, uncorrected)."""
    from scipy import stats

    lines = [("| setting | teams | n | target | gain trained | gain untrained | trained − untrained [95 % CI] "
             "| paired t p (uncorrected) |"), "|---|---|---|---|---|---|---|---|"]
    for setting, by_label in groups(results).items():
        for label, teams in by_label.items():
            if not all("probes_initial" in t for t in teams):
                continue
            for target in present(teams, TARGETS):
                a, b = raw_gains(teams, target), raw_gains(teams, target, "probes_initial")
                ok = np.isfinite(a) & np.isfinite(b)
                a, b = a[ok], b[ok]
                if not len(a):
                    continue
                p = float(stats.ttest_rel(a, b).pvalue) if len(a) > 1 else None
                lines.append(f"| {setting} | {label} | {len(a)} | {target} | {_f(a.mean())} | {_f(b.mean())} | "
                             f"{_ci(mean_ci(a - b))} | {_p(p)} |")
    return lines


def cut_table(results: list[dict]) -> list[str]:
    """Per agent: the drop of the team's paper metric when that agent's message is zeroed."""
    lines = [("| setting | teams | cut | n | drop: mean over teams [95 % bootstrap CI] | teams with drop > 0 "
             "| the cut matters |"), "|---|---|---|---|---|---|---|"]
    for setting, by_label in groups(results).items():
        for label, teams in by_label.items():
            for agent in teams[0]["cut"]:
                d = np.array([t["cut"][agent]["drop"] for t in teams])
                m = mean_ci(d)
                # The plan's rule is "the CI excludes 0"; which side matters too: a CI below 0 means the
                # team does better without that message (e.g. zeros are a quieter input than random noise).
                if not (np.isfinite(m[1]) and (m[1] > 0 or m[2] < 0)):
                    verdict = "no (CI includes 0)"
                else:
                    verdict = "yes: the cut costs" if m[1] > 0 else "yes, but the cut helps"
                name = agent if agent != "all" else "all agents (check)"
                lines.append(f"| {setting} | {label} | {name} | {len(d)} | {_ci(m, 2)} | {int((d > 0).sum())} of "
                             f"{len(d)} | {verdict} |")
    return lines


def team_table(results: list[dict]) -> list[str]:
    targets = present(results, PLAN_TARGETS)
    agents = max((len(r["cut"]) - 1 for r in results), default=0)
    lines = [("| setting | teams | seed | paper metric | " + "".join(f"gain {k} | " for k in targets)
              + f"cut drops (agent {', '.join(map(str, range(agents)))}; all) |"),
             "|---|---|---|---|" + "---|" * (len(targets) + 1)]
    for setting, by_label in groups(results).items():
        for label, teams in by_label.items():
            for t in teams:
                drops = ", ".join(_f(v["drop"], 2) for v in t["cut"].values())
                gains_ = [_f(t["probes"][k]["gain"]) if k in t["probes"] else "–" for k in targets]
                lines.append(f"| {setting} | {label} | {t['seed']} | {_f(t['paper_metric'], 2)} | "
                             + " | ".join(gains_) + f" | {drops} |")
    return lines


def method_header(n_teams: int, seeds: list[int], episodes: int) -> str:
    """The generated table's first lines: what ran and how the probes score, so the file stands alone."""
    return (f"# What the messages say\n\nGenerated by `hammer messages` (experiments/messages.py) following "
            f"docs/results/plan-messages.md: {n_teams} teams, evaluation seeds {seeds} x {episodes} episodes "
            "each (the runtime's numpy acting, in-process), messages on. u = the message as received (rl mode: "
            "after the Gaussian noise and clipping). Ridge probes per receiving agent and 2-D target slot, "
            "5-fold CV split by episode (alpha by 5-fold episode-split CV inside each training fold), score = "
            "held-out R² averaged over components, then slots, then receiving agents. Rows and tables marked "
            "exploratory are not in the plan and not tested with it.\n")


def to_markdown(results: list[dict], header: str = "") -> str:
    comps = comparisons(results)
    control = ("the requested shelf to fetch where it is in the robot's window, which it sees"
               if present(results, ("H_shelf",)) else "the receiver's nearest landmark, which it sees")
    parts = [header,
             "## Probes: held-out R² and the gain R²([o,u]) − R²([o])\n", *probe_table(results),
             "\n## The plan's comparisons: hammer-rl gain vs random gain (Holm across the pairs below)\n",
             *comparison_table(comps),
             f"\n## Control target V ({control})\n", *control_table(results),
             "\n## Exploratory target: the other agents' previous actions (X_actions, not in the plan)\n",
             *exploratory_target_table(results),
             "\n## Exploratory: trained vs untrained central agent, same recorded states (not in the plan)\n",
             *initial_table(results),
             "\n## Message cut per agent (paired per episode; drop = uncut − cut, > 0: the cut costs)\n",
             *cut_table(results), "\n## Per team\n", *team_table(results)]
    return "\n".join(parts) + "\n"


# ----- the figure ---------------------------------------------------------------------------------
def plot_episode(team: dict, out: Path) -> Path:
    """messages-episode.png: rows = receiving agents, columns = message components; the message sent
    (and, rl mode, the central policy's mean) and, dashed, the best-correlated hidden quantity rescaled
    to the message's mean and spread (so co-movement is visible whatever r is)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tr = team["episode"]
    msgs, mean = np.array(tr["msgs"]), np.array(tr["mean"])
    t, n, m = msgs.shape
    fig, axes = plt.subplots(n, m, figsize=(3.2 * m, 2.3 * n), sharex=True, sharey=True, squeeze=False)
    steps = np.arange(1, t + 1)
    for i in range(n):
        for c in range(m):
            ax, b = axes[i, c], tr["best"][i][c]
            ax.plot(steps, msgs[:, i, c], color="C0", lw=1.2, label="message sent")
            if team["label"].startswith("hammer-rl"):
                ax.plot(steps, mean[:, i, c], color="C0", lw=0.8, alpha=0.5, label="policy mean")
            if b["name"] is not None:
                over = np.array([np.nan if v is None else v for v in b["overlay"]], dtype=float)
                ax.plot(steps, over, "--", color="C3", lw=1.2, label="best-correlated hidden quantity (rescaled)")
                ax.set_title(f"agent {i} u[{c}] ~ {b['name']}\nr = {b['r']:+.2f} over all recorded steps", fontsize=7)
            ax.axhline(0, color="black", lw=0.4)
            ax.set_ylim(-1.6, 1.6)
            if i == n - 1:
                ax.set_xlabel("step")
    axes[0, 0].legend(fontsize=6, loc="lower left")
    fig.suptitle(f"{team['setting']}, {team['label']} seed {team['seed']}: one episode "
                 f"(paper metric {tr['paper_metric']:.2f})", fontsize=9)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out


# ----- the whole analysis -------------------------------------------------------------------------
@dataclass
class Teams:
    """The runs given, sorted: the teams analysed and why the others were left out."""

    teams: list[Path]
    no_messages: list[Path]
    no_weights: list[Path]


def select_teams(paths: list[Path], labels: list[str] | None = None) -> Teams:
    """Every run under `paths` whose variant sends messages (hammer, random) and whose final/ weights
    were archived with it (IL and centralised teams have no message to probe); with `labels`, only
    runs whose label (`experiments.runs.Run.label`, e.g. hammer-rl-m4) starts with one of them."""
    import json

    from hammer.experiments.runs import Run, find_runs

    found = Teams([], [], [])
    for run in find_runs(paths):
        cfg = json.loads((run / "config.json").read_text())
        label = Run(run, cfg, *([np.zeros(0)] * 3), finished=True).label
        if labels is not None and not any(label.startswith(p) for p in labels):
            continue
        if cfg.get("variant") not in ("hammer", "random"):
            found.no_messages.append(run)
        elif not (run / "final" / "local.safetensors").is_file():
            found.no_weights.append(run)
        else:
            found.teams.append(run)
    return found


def analyse(teams: list[Path], seeds: list[int], episodes: int, previous: list[dict] | None = None,
            progress=None, figure_seed: int = 0, jobs: int = 1, save=None) -> list[dict]:
    """Every team's result; a team whose weights, evaluation and analysis version match a previous
    result (the committed JSON) is not recomputed, so redrawing the tables costs nothing. jobs > 1:
    the teams to compute run in that many processes (each team's result does not depend on the others
    or on the order: the same JSON, tested). save(results so far) after each computed team, so an
    analysis cut short keeps what it finished (`hammer messages` re-reads it as its cache)."""
    from hammer.experiments.messages import TeamActor, analyse_team, team_key

    cached = {r["key"]: r for r in previous or []}
    todo: dict[int, tuple[Path, bool]] = {}
    out: list[dict | None] = []
    for run in teams:
        actor = TeamActor(run)
        wants_episode = actor.data.get("seed") == figure_seed and actor.data.get("variant") == "hammer"
        hit = cached.get(team_key(actor, seeds, episodes))
        if hit is not None and (not wants_episode or "episode" in hit):
            out.append({**hit, "run": str(run)})
        else:
            out.append(None)
            todo[len(out) - 1] = (run, wants_episode)
    done = 0

    def report(k: int, how: str) -> None:
        nonlocal done
        done += 1
        if save is not None and how == "analysed":
            save([r for r in out if r is not None])
        if progress is not None:
            progress(done, len(teams), out[k], how)

    for k, res in enumerate(out):
        if res is not None:
            report(k, "cached")
    if jobs <= 1 or len(todo) <= 1:
        for k, (run, ep) in todo.items():
            out[k] = analyse_team(run, seeds, episodes, keep_episode=ep)
            report(k, "analysed")
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        # spawn: a fresh interpreter per worker (no forked torch or BLAS thread state)
        with ProcessPoolExecutor(min(jobs, len(todo)), mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = {pool.submit(analyse_team, run, seeds, episodes, keep_episode=ep): k
                       for k, (run, ep) in todo.items()}
            for f in as_completed(futures):
                out[futures[f]] = f.result()
                report(futures[f], "analysed")
    return out


def figure_paths(results: list[dict], figure: Path, seed: int = 0) -> dict[Path, dict]:
    """One figure per setting: its hammer-rl team of training seed `seed` (hammer-backprop if it has
    none); `figure` itself for one setting, `<stem>-<setting>.png` beside it for several."""
    picks = {}
    for setting, by_label in groups(results).items():
        for prefix in ("hammer-rl", "hammer-backprop"):
            team = next((t for lab, ts in by_label.items() if lab.startswith(prefix) for t in ts
                         if t["seed"] == seed and "episode" in t), None)
            if team is not None:
                picks[setting] = team
                break
    if len(picks) == 1:
        return {figure: next(iter(picks.values()))}
    slug = lambda s: "".join(ch if ch.isalnum() or ch in "=._" else "-" for ch in s).strip("-")
    return {figure.with_name(f"{figure.stem}-{slug(s)}{figure.suffix}"): t for s, t in picks.items()}
