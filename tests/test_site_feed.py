"""The site feed: what a fleet's central agent sees that no robot observes (a warehouse's requested
shelves and goals), from the site (serve/site_feed.py, `hammer.site.SiteFeed`; docs/fleet.md "The site
feed"). Real Zenoh on 127.0.0.1, a real trained rware team exported with `hammer export`, real rware
rows, real processes for the fleets. What is asserted is where each column of the central agent's
state came from, the silent rule (held, then zeros, named) and who may publish the feed."""

from __future__ import annotations

import contextlib
import json
import logging
import re
import shutil
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from hammer.central_agent.fleet_central import FleetCentral
from hammer.protocol import codec
from hammer.protocol.binding import check_key
from hammer.protocol.dims import Dims
from hammer.protocol.errors import KeyMismatchError, NonFiniteError, ProtocolError
from hammer.protocol.fields import HEADER_BYTES
from hammer.protocol.schemas import SiteState, Uplink
from hammer.protocol.session import HammerSession, TransportConfig, free_loopback_port, loopback_endpoint
from hammer.serve.bundle import CENTRAL, export_bundle, load_bundle
from hammer.serve.edge_agent import EdgeAgent

from hammer.site import SiteFeed
from tests.runtime_helpers import ENV, ROOT, run_block_beside_serve, trained_run

pytestmark = pytest.mark.timeout(240)
RUN = "site-feed"


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    """A briefly trained rware-tiny-2ag team (backprop: its messages are the central network's mean,
    deterministic), exported as `hammer export` does."""
    d = tmp_path_factory.mktemp("warehouse")
    trained_run(d / "run", ("episodes=8", "env_kwargs.max_steps=100", "num_envs=4", "rollout_steps=50",
                            "central_mode=backprop", "seed=3"), preset="rware-tiny-2ag")
    return export_bundle(d / "run", d / "bundle").path


def _wait(cond, timeout=10.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.02)
    return False


def _rows(b) -> np.ndarray:
    """Real rware rows of the team's warehouse after a few random steps: (N, D)."""
    from hammer.learning.run_env import make_env

    cfg = b.config(num_envs=1)
    with make_env(cfg) as env:
        obs, _ = env.reset(11)
        rng = np.random.default_rng(0)
        for _ in range(5):
            obs = env.step(rng.integers(0, 5, (1, cfg.n_agents))).obs
    return obs[0]


def test_a_site_state_is_typed_capped_and_bound_to_its_key(bundle):
    b = load_bundle(bundle)
    d, local = b.env_spec_data["obs_dim"], b.env_spec_data["local_obs_dim"]
    c = SiteFeed.columns(bundle)
    assert c == d - local > 0
    cols = _rows(b)[0, local:][None]
    msg = SiteState(step=3, env_idx=np.zeros(1, np.int64), cols=cols)
    back = codec.decode(codec.encode(msg), SiteState, Dims(num_envs=1, site_dim=c))
    assert np.array_equal(back.cols, cols) and back.step == 3
    with pytest.raises(ProtocolError, match="site_dim"):  # another team's width: refused, named
        codec.decode(codec.encode(msg), SiteState, Dims(num_envs=1, site_dim=c + 1))
    with pytest.raises(NonFiniteError):
        SiteState(env_idx=np.zeros(1, np.int64), cols=np.full((1, c), np.nan, np.float32))
    # the size a receiver that declares the feed's width refuses beyond, before decoding
    assert SiteState.cap_for_dims(Dims(num_envs=1, site_dim=c)) == HEADER_BYTES + 8 + 4 * c
    # bound to its key: only the site's, and nothing else on a robot's key
    check_key(SiteState(env_idx=np.zeros(1, np.int64), cols=cols), "site/state")
    with pytest.raises(KeyMismatchError, match="sender"):
        check_key(SiteState(env_idx=np.zeros(1, np.int64), cols=cols, sender="local-1"), "site/state")
    with pytest.raises(KeyMismatchError, match="type"):
        check_key(SiteState(env_idx=np.zeros(1, np.int64), cols=cols), "agent/up/1")
    with pytest.raises(KeyMismatchError, match="type"):
        check_key(Uplink(env_idx=np.zeros(1, np.int64), agent=1, obs=np.zeros((1, d), np.float32)), "site/state")


@contextlib.contextmanager
def _central_agent(port: int, b, bundle, site_hold_s: float):
    """A fleet's central agent (50 Hz, no world: its own clock) in a thread, with a session of its own."""
    s = HammerSession(RUN, TransportConfig(listen=["tcp/127.0.0.1:0"], connect=[loopback_endpoint(port)]),
                      sender="central")
    with s:
        central = FleetCentral(s, b.config(num_envs=1), b.env_spec(), (bundle / CENTRAL).read_bytes(), hz=50,
                               missing_after_s=2.0, site_hold_s=site_hold_s)
        t = threading.Thread(target=central.run, daemon=True)
        t.start()
        try:
            yield central
        finally:
            central.stop_reason = "test over"
            t.join(5)
        assert not t.is_alive()


def test_the_central_agent_composes_its_state_from_the_robots_and_the_feed_then_holds_then_zeros(bundle, caplog):
    """Two robots on the SDK uplink their own columns only (L floats), the site feed (the SDK) the rest:
    the central agent's rows are the warehouse's rows exactly. The feed stops: held for site_hold_s,
    then zeros (logged, counted: the messages then differ), and back when it is."""
    caplog.set_level(logging.INFO)
    b = load_bundle(bundle)
    local = b.env_spec_data["local_obs_dim"]
    rows = _rows(b)
    port = free_loopback_port()
    with HammerSession(RUN, TransportConfig(listen=[loopback_endpoint(port)]), sender="hub"), \
            _central_agent(port, b, bundle, site_hold_s=0.4) as central:
        robots = [EdgeAgent(bundle, i, run_id=RUN, connect=loopback_endpoint(port), wait=True) for i in range(2)]
        with SiteFeed(bundle, run_id=RUN, connect=loopback_endpoint(port), wait=True) as site, \
                robots[0], robots[1]:
            with pytest.raises(ValueError, match=f"state: expected {SiteFeed.columns(bundle)} finite floats"):
                site.publish(np.zeros(3))
            with pytest.raises(ValueError, match="NaN"):
                site.publish(np.full(SiteFeed.columns(bundle), np.nan))

            def feed_and_act() -> None:
                site.publish(rows[0, local:])
                for i, r in enumerate(robots):
                    r.act(rows[i, :local])  # a robot's own columns only: it never sees the rest

            assert _wait(lambda: (feed_and_act(), np.array_equal(central.obs[0], rows))[1]), \
                "the central agent's rows are not the robots' columns plus the feed's"
            assert central.site_presence.present[0] and central.site_presence.leaves == 0
            silent_before = central.site_silent_ticks  # ticks before the feed was first heard: zeros too
            with_feed = central.net.message_mean(central.acting.global_state(central.obs.copy(), central.prev))

            # the feed goes silent, the robots go on: held for site_hold_s, then zeros in every row
            stopped = time.monotonic()
            assert _wait(lambda: ([r.act(rows[i, :local]) for i, r in enumerate(robots)],
                                  not central.site_presence.present[0])[1])
            assert time.monotonic() - stopped >= 0.3  # held first (site_hold_s 0.4)
            assert _wait(lambda: (central.obs[0, :, local:] == 0).all() and central.site_silent_ticks > silent_before)
            assert np.array_equal(central.obs[0, :, :local], rows[:, :local])  # the robots' own columns stay
            without = central.net.message_mean(central.acting.global_state(central.obs.copy(), central.prev))
            assert not np.allclose(with_feed, without)  # the feed is what the messages are made from
            counters = central.counters()
            assert counters["site_silences"] == 1 and counters["site.joined"] == 1
            assert counters["site.absent_max_s"] >= 0
            # back: the feed's columns again
            assert _wait(lambda: (feed_and_act(), np.array_equal(central.obs[0], rows))[1])
            assert central.site_presence.rejoins == 1
    text = caplog.text
    assert "site missing: nothing from it" in text and "the site feed is silent" in text
    assert re.search(r"site rejoined after [\d.]+ s silent", text)


def test_a_warehouse_team_runs_as_a_fleet_with_the_world_as_its_site(bundle, tmp_path):
    """`hammer serve BUNDLE --realtime 20` on an exported rware team: the world, the central agent and
    one `hammer local --bundle ... --fleet` per robot; the world publishes the feed as the site, the
    central agent takes it, nothing is degraded."""
    run = tmp_path / "fleet"
    r = subprocess.run([sys.executable, "-P", "-m", "hammer.cli", "serve", str(bundle), "--realtime", "20",
                        "--seconds", "8", "--run-dir", str(run), "--runtime", "site_hold_s=2"],
                       cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=180, check=False)
    assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
    s = json.loads((run / "summary.json").read_text())
    assert s["completed"] and not s["degraded"], s["degraded_reasons"]
    site = s["site"]
    assert site["published_by_world"] > 100 and site["states"] > 100 and not site["never_heard"], site
    assert site["silences"] == 0, site
    assert all(rb["fresh"] > 0 and rb["msg_fresh"] > 0 for rb in s["robots"].values()), s["robots"]
    plan = json.loads((run / "fleet.json").read_text())
    assert plan["plan"]["site_hold_s"] == 2 and "--site-hold-s 2.0" in plan["commands"]["central"]
    assert "local-0" in plan["commands"] and "--fleet" in plan["commands"]["local-0"]


def _docs_block() -> tuple[str, str]:
    text = (ROOT / "docs" / "fleet.md").read_text()
    section = text[text.index("## The site feed"):]
    code = re.search(r"```python\n(.*?)```", section, re.DOTALL).group(1)
    command = re.search(r"`(hammer serve bundles/lib-rware --realtime [^`]*)`", section).group(1)
    return code, command


def test_the_docs_site_example_runs_against_a_served_fleet(bundle, tmp_path):
    """docs/fleet.md's site feed block, as it stands (only the port made free), against the command it
    names (`--external-site`: the site is the block), from a folder of the user's own; then SIGTERM to
    `hammer serve`: the summary's site has the block's states."""
    code, command = _docs_block()
    port = str(free_loopback_port())
    shutil.copytree(bundle, tmp_path / "bundles" / "lib-rware")
    r, serve, out = run_block_beside_serve(command, code, tmp_path, "site-w", port)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.split() == ["60"]
    assert serve.returncode == 0, out[-2000:]
    assert "waiting for the site feed: hammer.site.SiteFeed('bundles/lib-rware'" in out, out[-2000:]
    s = json.loads((tmp_path / "runs" / "site-w" / "summary.json").read_text())
    assert s["interrupted"] and s["site"]["states"] > 0 and not s["site"]["never_heard"], s["site"]
    assert s["site"]["published_by_world"] is None  # the world did not publish it: the block did
    assert s["site"]["recorded_by_world"] > 0  # the world wrote the warehouse's columns that the block read


@pytest.fixture(scope="module")
def trained_bundle(tmp_path_factory):
    """The archived trained warehouse team (rware-tiny-2ag hammer rl, seed 0, 5M env steps), exported."""
    run = ROOT / "docs" / "results" / "runs" / "rware5m-2" / "rware-tiny-2ag-hammer-rl-ep10000-s0"
    return export_bundle(run, tmp_path_factory.mktemp("trained") / "bundle").path


def test_a_site_elsewhere_publishes_the_warehouse_s_current_columns_not_its_layout_at_reset(trained_bundle, tmp_path):
    """A trained warehouse team (the archived rware-tiny-2ag hammer rl team, exported) served with
    `--external-site`: the world writes the env's current central-only columns for the site
    (RUN/warehouse.npy, whenever they change) and a site beside it (`hammer.site.simulated_warehouse` +
    `SiteFeed`) publishes them. What the site published follows the warehouse: not its layout at
    reset (the world's env, reset with the team's seed), and changing as the robots carry shelves
    and deliver; the central agent took the states."""
    from hammer.deploy.fleet_launch import FleetPlan, run_fleet
    from hammer.learning.run_env import make_env

    from hammer.site import simulated_warehouse

    bundle = trained_bundle
    b = load_bundle(bundle)
    cfg, local = b.config(num_envs=1), b.env_spec_data["local_obs_dim"]
    with make_env(cfg) as env:
        reset = env.reset(cfg.seed)[0][0, 0, local:]
    run, sent = tmp_path / "fleet", []

    def site() -> None:
        assert _wait(lambda: (run / "fleet.json").is_file(), 60), "the fleet did not start"
        connect = "tcp/" + json.loads((run / "fleet.json").read_text())["hub"].split("/", 1)[1]
        wms_state = simulated_warehouse(run)
        with SiteFeed(bundle, run_id=run.name, connect=connect, wait=True) as feed:
            while not (run / "summary.json").is_file():
                state = wms_state()
                if state is not None and feed.publish(state):
                    sent.append(state)
                time.sleep(0.05)

    t = threading.Thread(target=site, daemon=True)
    t.start()
    s = run_fleet(FleetPlan(bundle=bundle, hz=20, seconds=10, site_external=True), run)
    t.join(10)
    assert s["completed"] and not s["degraded"], s["degraded_reasons"]
    site_view = s["site"]
    assert site_view["recorded_by_world"] > 150 and site_view["published_by_world"] is None, site_view
    assert site_view["states"] > 100 and not site_view["never_heard"], site_view
    assert len(sent) > 100 and all(c.shape == reset.shape for c in sent)
    assert not all(np.array_equal(c, reset) for c in sent), "the site's feed stayed at the warehouse's layout at reset"
    assert len({c.tobytes() for c in sent}) >= 3, "the feed did not follow the warehouse"


def test_the_warehouse_record_is_rewritten_only_when_the_columns_change(tmp_path):
    """The world hands the record every tick's columns; the file (what the site reads) is replaced
    only when they differ from the last written, and a reader always gets the latest."""
    from hammer.serve.site_feed import WarehouseRecord

    from hammer.site import simulated_warehouse

    record, read = WarehouseRecord(tmp_path), simulated_warehouse(tmp_path)
    assert read() is None
    a, b = np.zeros(5, np.float32), np.arange(5, dtype=np.float32)
    for cols in (a, a, a.copy(), b, b, a):
        assert record.publish(cols)
        assert np.array_equal(read(), cols)
    assert record.writes == 3
    assert [p.name for p in tmp_path.iterdir()] == ["warehouse.npy"]


def test_a_team_without_a_feed_or_a_fleet_without_one_is_told_in_one_line(bundle, tmp_path):
    """`--external-site` with nobody publishing: the fleet runs, the central agent's state has zeros in
    the site's columns all along, and the verdict says so by name."""
    from hammer.deploy.fleet_launch import FleetPlan, run_fleet

    s = run_fleet(FleetPlan(bundle=bundle, hz=20, seconds=4, site_external=True), tmp_path / "nobody")
    assert s["completed"] and s["site"]["never_heard"] and s["site"]["states"] == 0, s["site"]
    assert s["site"]["silent_ticks"] > 0
    assert any(r.startswith("the site feed never reached the central agent") for r in s["degraded_reasons"]), s


def test_only_the_site_may_publish_the_feed_in_a_secure_fleet_not_a_stolen_robot_key(bundle, tmp_path):
    """`hammer serve --realtime --secure --external-site`: the launcher makes the `site` identity, and
    the access rules let only it publish `site/state`. A thief with robot 1's stolen identity floods
    forged site states on `site/state` (dropped by the rules: the central agent never takes one) and
    on robot 1's own uplink key (refused there, named in the verdict as a holder of local-1's key);
    then the real site, with its own identity, reaches the central agent."""
    from hammer.deploy.fleet_launch import FleetPlan, run_fleet
    from hammer.protocol.identity import identity_dir
    from hammer.protocol.schemas import CentralMsg
    from hammer.runtime.settings import RuntimeSettings

    n, c = 2, SiteFeed.columns(bundle)
    run = tmp_path / "fleet-secure"
    plan = FleetPlan(bundle=bundle, hz=20, seconds=20, secure=True, site_external=True, max_absence_s=60)
    seen: dict[str, dict] = {}
    out = {"forged": 0}

    def watch(board, t: float) -> None:
        central = board.heartbeats.get("central")
        if central is not None:
            seen["central"] = dict(central.counters)

    def attack_then_site() -> None:  # the launcher takes the main thread (it handles SIGTERM)
        assert _wait(lambda: (run / "fleet.json").is_file(), 60), "the fleet did not start"
        hub = json.loads((run / "fleet.json").read_text())["hub"]
        connect = "tcp/" + hub.split("/", 1)[1]
        stolen = RuntimeSettings(run_id=run.name, secure=True, secure_hub=True).secured(
            TransportConfig(mode="client", connect=[connect]), "local-1", None, n,
            identity_directory=identity_dir(run))
        forged = SiteState(env_idx=np.zeros(1, np.int64), cols=np.full((1, c), 7.0, np.float32))
        with HammerSession(run.name, stolen, sender="local-1") as s:
            k = s.keys
            msgs = s.subscribe(k.msg(1), CentralMsg)  # robot 1's: the stolen key does its robot's job
            feed, own = s.publisher(k.site_state(), block=False), s.publisher(k.up(1), block=False)
            assert _wait(lambda: bool(msgs.drain()), 60), "the central agent never served robot 1"
            end = time.monotonic() + 4
            while time.monotonic() < end:
                feed.publish(forged)
                own.publish(forged)
                out["forged"] += 1
                time.sleep(0.02)
        time.sleep(2.5)  # a heartbeat of the central agent after the last forgery
        out["central_after_thief"] = dict(seen.get("central", {}))
        with SiteFeed(bundle, run_id=run.name, connect=connect, identity=identity_dir(run), wait=True) as site:
            end = time.monotonic() + 4
            while time.monotonic() < end:
                site.publish(np.zeros(c, np.float32))
                time.sleep(0.05)
            out["real"] = site.counts["published"]

    t = threading.Thread(target=attack_then_site, daemon=True)
    t.start()
    s = run_fleet(plan, run, on_tick=watch)
    t.join(30)
    assert (identity_dir(run) / "site.pem").is_file() and (identity_dir(run) / "site.key").is_file()
    assert out["forged"] > 100 and out["real"] > 40, out
    before = out["central_after_thief"]
    assert before.get("site_states", -1) == 0 and before.get("site.joined") == 0, before  # no forgery taken
    site = s["site"]
    assert site["states"] > 0 and not site["never_heard"], site  # the real site's, after
    # the forgeries on robot 1's own key were refused there, and named as a holder of local-1's key
    assert sum(s["rejected_on"]["local-1"]["central"].values()) > 0, s["rejected_on"]
    assert any("refused on local-1's own keys" in r and "stolen" in r for r in s["degraded_reasons"]), s


def test_training_simulates_the_feed_s_absence_as_it_simulates_a_missing_robot():
    """site_missing_prob: in windows of missing_window steps the central agent's state has zeros in
    the site's columns of every row (the fleet's silent rule), decided by a hash as a robot's absence
    is; the robots' absences are the same with or without it; 0 (the default) changes nothing; an env
    without a site feed refuses it in one line."""
    from hammer.envs.registry import make_vec_env
    from hammer.learning.central_acting import CentralActing
    from hammer.learning.config import ConfigError, merge_config
    from hammer.learning.team import Team

    over = ["num_envs=4", "missing_prob=0.2", "missing_window=5"]
    cfg = merge_config("rware-tiny-2ag", overrides=[*over, "site_missing_prob=0.3"])
    plain = CentralActing.from_config(merge_config("rware-tiny-2ag", overrides=over))
    acting = CentralActing.from_config(cfg)
    env = make_vec_env(cfg.env, cfg.n_agents, 1, env_kwargs=cfg.env_kwargs)
    spec = env.spec
    local = spec.local_obs_dim
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(16, 2, spec.obs_dim)).astype(np.float32)
    prev = rng.normal(size=(16, 2, spec.action_dim)).astype(np.float32)
    idx = np.arange(16)
    there = np.stack([acting.training_site_presence(s, idx) for s in range(1, 1001)])
    assert 0.27 < 1 - there.mean() < 0.33 and (there[:5] == there[0]).all() and (there[5:10] == there[5]).all()
    for step in (1, 6, 11, 16):
        state = acting.training_state(obs, prev, step, idx, local)
        rows = state[:, :2 * spec.obs_dim].reshape(16, 2, spec.obs_dim)
        robots = acting.training_presence(step, idx)
        assert np.array_equal(robots, plain.training_presence(step, idx))  # the robots' absences unchanged
        gone = ~there[step - 1]
        assert (rows[gone][:, :, local:] == 0).all()
        both = ~gone[:, None] & robots
        assert np.array_equal(rows[both], obs[both])  # the feed there, the robot there: the row as is
        # the default: exactly what it was
        assert np.array_equal(plain.training_state(obs, prev, step, idx, local),
                              plain.global_state(obs, prev, plain.training_presence(step, idx)))
    assert plain.training_site_presence(3, idx) is None
    with pytest.raises(ConfigError, match="site_missing_prob: .* has no site feed"):
        cn = merge_config("cn3", overrides=["site_missing_prob=0.1"])
        Team(cn, make_vec_env(cn.env, cn.n_agents, 1, env_kwargs=cn.env_kwargs).spec)


def test_hammer_up_reproduces_hammer_train_with_the_feed_s_absences(tmp_path):
    """The trainer, `hammer up`'s central server and its learner (which rebuilds the states it trains
    on) take the same feed away at the same steps: the same episodes and the same weights."""
    from safetensors.numpy import load as load_safetensors

    sets = ("env_kwargs.max_steps=100", "num_envs=4", "rollout_steps=50", "site_missing_prob=0.4", "missing_window=10")
    common = ["--preset", "rware-tiny-2ag", "--central-mode", "rl", "--episodes", "8",
              *(a for field in sets for a in ("--set", field))]
    up, tr = tmp_path / "up", tmp_path / "train"

    def hammer(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "hammer.cli", *args], cwd=ROOT, env=ENV, capture_output=True,
                              text=True, timeout=600, check=False)

    r = hammer("up", *common, "--run-dir", str(up), "--no-dashboard", "--runtime", "msg_deadline_ms=5000",
               "--runtime", "act_deadline_ms=10000")
    assert r.returncode == 0, r.stderr[-2000:]
    # the trainer in process, as `hammer train` runs it
    trained_run(tr, ("variant=hammer", "central_mode=rl", "episodes=8", *sets, "torch_threads=1"),
                preset="rware-tiny-2ag")
    assert json.loads((tr / "config.json").read_text())["site_missing_prob"] == 0.4
    for part in ("local", "central"):
        wa = load_safetensors((up / "final" / f"{part}.safetensors").read_bytes())
        wb = load_safetensors((tr / "final" / f"{part}.safetensors").read_bytes())
        for key in wa:
            np.testing.assert_array_equal(wa[key], wb[key], err_msg=f"{part}/{key}")


def test_a_site_issues_the_feed_a_kept_identity_as_it_does_a_robot(tmp_path):
    """`hammer site issue DIR site`: the site feed's identity is kept like a robot's (an external
    warehouse management system keeps its files across fleet restarts); without one, the fleet makes
    the feed's certificate anew from the site CA (the world publishes it); a revoked one is dropped
    from the trust; the fleet's own roles are still not issued."""
    from hammer.protocol.identity import SiteError, init_site, issue_robot, revoke_robot, site_run_identities

    site = init_site(tmp_path / "site")
    run_ids = tmp_path / "run-ids"
    site_run_identities(site, run_ids, ["env", "central", "site"])
    made = (run_ids / "site.pem").read_bytes()
    ident = issue_robot(site, "site")
    kept = ident.cert.read_bytes()
    assert ident.cert == site / "robots" / "site" / "site.pem" and kept != made
    issuer = (site / "robots" / "site" / "issuer.pem").read_bytes()
    assert issuer in (site / "trust.pem").read_bytes()
    site_run_identities(site, run_ids, ["env", "central", "site"])  # a restart: the kept files, as they are
    assert (run_ids / "site.pem").read_bytes() == kept
    assert (run_ids / "site.key").read_bytes() == (site / "robots" / "site" / "site.key").read_bytes()
    revoke_robot(site, "site")
    assert issuer not in (site / "trust.pem").read_bytes()
    site_run_identities(site, run_ids, ["env", "central", "site"])
    assert (run_ids / "site.pem").read_bytes() != kept
    with pytest.raises(SiteError, match="site feed's, site"):
        issue_robot(site, "central")


def test_an_il_warehouse_team_runs_as_a_fleet_without_a_feed(tmp_path):
    """Variant il has no central agent, so no one needs the site's columns: the fleet runs with no feed
    (no `site` in the summary), each robot on its own columns."""
    from hammer.deploy.fleet_launch import FleetPlan, run_fleet

    trained_run(tmp_path / "run", ("episodes=4", "env_kwargs.max_steps=100", "num_envs=4", "rollout_steps=50",
                                   "variant=il"), preset="rware-tiny-2ag")
    bundle = export_bundle(tmp_path / "run", tmp_path / "bundle").path
    s = run_fleet(FleetPlan(bundle=bundle, hz=20, seconds=4), tmp_path / "fleet")
    assert s["completed"] and not s["degraded"] and s["site"] is None, s["degraded_reasons"]
    assert all(r["fresh"] > 0 for r in s["robots"].values()), s["robots"]


def test_the_feed_s_own_link_cut_across_namespaces_and_restored(bundle, tmp_path):
    """`hammer bench fleet --trials site:3`: a secure warehouse fleet on a LAN of namespaces, the site
    (`hammer.site.SiteFeed`, its copy of its identity) in a namespace of its own; its switch port down
    3 s. The central agent loses the feed (held, then zeros: a silence counted) and takes it again
    within the recovery contract once the port is back; no robot is cut."""
    from tests.runtime_helpers import netns_reason

    reason = netns_reason(("ip",))
    if reason:
        pytest.skip(reason)
    from hammer.benchmarks.fleet_bench import CONTRACT, run_trials, trial_line
    from hammer.benchmarks.netns import NetnsUnavailable

    try:
        r = run_trials(bundle, tmp_path, [("site", 3.0, 1)], hz=20, secure=True, results=tmp_path / "trials.jsonl",
                       progress=lambda line: None)
    except NetnsUnavailable as e:
        pytest.skip(str(e))
    (t,) = r["trials"]
    assert t["kind"] == "site" and t["cut"] == ["site"], t
    assert not t["stranded"] and t["back_max_s"] <= CONTRACT["back_s"], trial_line(t)
    site = r["fleets"][0]["summary"]["site"]
    assert site["silences"] >= 1 and site["longest_silence_s"] >= 2.0 and site["states"] > 0, site
    assert site["published_by_world"] is None  # the namespace's site published it, not the world


def test_the_simulated_reference_applies_the_fleet_s_rules_to_the_same_team(trained_bundle):
    """benchmarks/site_play.simulate, the reference without a fleet, on the archived trained team: a
    feed silent from the first tick to the end with no hold is the feed's columns zeros all along
    (`zeros`), episode for episode; the same kind twice plays the same episodes (seeds and streams);
    a robot cut (its action held, then the default; its row zeros for the central agent) plays other
    episodes than the live team, with fewer deliveries."""
    from hammer.benchmarks.site_play import simulate

    length = load_bundle(trained_bundle).env_spec().max_steps
    whole = simulate(trained_bundle, "site", 4, cut_at=0.0, cut_s=length / 20, site_hold_s=0.0, copies=4)
    assert whole == simulate(trained_bundle, "zeros", 4, cut_at=0.0, cut_s=0.0, copies=4) and len(whole) == 4
    live = simulate(trained_bundle, "live", 4, cut_at=5.0, cut_s=10.0, copies=4)
    assert live == simulate(trained_bundle, "live", 4, cut_at=5.0, cut_s=10.0, copies=4) and sum(live) > 0
    cut = simulate(trained_bundle, "port", 4, cut_at=5.0, cut_s=10.0, copies=4)
    assert sum(cut) < sum(live), (cut, live)
