"""`hammer serve --realtime HZ`: a trained team run as a fleet, every robot its own process.

The processes (docs/fleet.md): the realtime world (env_host/world.py, the simulator stepping at HZ
on the robots' latest actions), the fleet's central agent (central_agent/fleet_central.py, answering the
state of each of the world's ticks with a message per robot, which the world puts into that tick's
observations) and one robot per agent (`hammer local --bundle ... --fleet`: serve/edge_agent.py,
torch-free). No robot waits for anyone:
a robot that is paused, killed or cut off costs the others nothing, which is what the summary
shows (per robot: control rate, action and message ages, defaults, fallbacks; joins, leaves and
rejoins by name). Training stays lock-stepped (`hammer up`); this is deployment.

The topology (docs/fleet.md "Running a fleet"): the launcher's own Zenoh session is the fleet's
router, listening on loopback and on every `--listen` endpoint; the world, the central agent, the
policy server and every robot are Zenoh clients of it. No process ever dials another but the
router, so a robot's link that fails and returns is one client reconnecting to one router, and a
robot whose lease expires is one client link closed: no other robot's traffic takes part. In a
secure fleet the router holds the run's `hub` identity and checks the access rules on every hop,
and every role checks them again on its own link.

The launcher opens the router and runs the one launch loop of every launcher (deploy.launcher.Launcher:
no waiting for liveliness here, robots join when they can): it starts the roles, restarts a robot,
the central agent or the policy server that dies (up to 3 times, then goes on without it; not one
that `--chaos` killed on purpose: `kill:local-1@t=5,for=3` restarts it after 3 s), fires the
`--chaos` events on time (from the world's first tick), and at the end (the world's episodes or
seconds, Ctrl-C or SIGTERM) stops every role; then it writes summary.json.

Hot updates: the launcher also runs the fleet's policy server (`hammer fleet-policy`, the
`serve.policy_server.PolicyServer` of a lock-stepped served run) following RUN/pushes.json, and
writes what `hammer push` / `hammer rollback` check a push against, as `hammer serve` does for a
lock-stepped run: runtime.json (mode eval, the bundle as policy_dir), config.json and env_spec.json.
Each robot and the central agent switch on their own once they hold a pushed version (docs/fleet.md);
the launcher records every switch it sees in their heartbeats (summary.json: `version_switches`).
"""

from __future__ import annotations

import json
import logging
import shlex
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path

from hammer.deploy.fleet_verdict import fleet_verdict
from hammer.deploy.launcher import Board, Launcher, UpError, stop_on_signals
from hammer.deploy.supervisor import RoleSpec, role_args
from hammer.protocol.access import HUB, LAUNCHER, POLICY
from hammer.protocol.schemas import Heartbeat
from hammer.protocol.session import HammerSession, TransportConfig, free_loopback_port, loopback_endpoint
from hammer.protocol.structs import replace
from hammer.protocol.transport_log import refused_counts, watch_refused
from hammer.runtime.clock import MSG_WAIT_S, SITE_HOLD_S
from hammer.runtime.settings import refuse_plain_beyond_loopback, runtime_items

log = logging.getLogger("hammer.fleet")


@dataclass
class FleetPlan:
    """What a fleet run is: the bundle, its clock and its bounds (all times in seconds)."""

    bundle: Path
    hz: float = 20.0
    seconds: float | None = 60.0
    episodes: int | None = None
    hold_s: float = 0.5  # the world holds a robot's last action this long, then applies the default
    missing_after_s: float = 0.5  # the central agent counts a robot silent this long as missing (zeros)
    max_msg_age_s: float = 0.5  # a robot acts on a central message no older than this, else its fallback
    msg_wait_s: float = MSG_WAIT_S  # a tick's observations wait this long for the central agent's messages of it
    site_hold_s: float = SITE_HOLD_S  # the central agent holds the site feed this long, then uses zeros
    site_external: bool = False  # a real site publishes the feed (`hammer.site.SiteFeed`), not the world
    seed: int | None = None
    chaos: list[str] = field(default_factory=list)
    hub_port: int = 0
    listen: list[str] = field(default_factory=list)  # more endpoints for the hub (robots on other machines)
    external: list[int] = field(default_factory=list)  # robots started elsewhere (the SDK, `hammer local --fleet`)
    secure: bool = False  # mutual TLS with the run's identities (RUN/identity/) and per-role access rules
    insecure: bool = False  # accept plain traffic beyond loopback (on a network you trust)
    max_absence_s: float = 10.0  # a robot missing longer than this at a time makes the run degraded
    runtime: dict = field(default_factory=dict)  # RuntimeSettings fields from `--runtime` (runtime_items)
    timeline: Path | None = None  # the world appends per-robot totals here once a second (benches)
    site: Path | None = None  # secure: identities from this site (`hammer site init`), kept across restarts

    def check(self) -> None:
        for name in ("hz", "hold_s", "missing_after_s", "max_msg_age_s", "max_absence_s", "site_hold_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}: must be > 0, got {getattr(self, name)}")
        if not 0 <= self.msg_wait_s < 1 / self.hz:
            raise ValueError(f"msg_wait_s: must be >= 0 and under a tick ({1 / self.hz:g} s), got {self.msg_wait_s}")
        if self.seconds is None and self.episodes is None:
            raise ValueError("a fleet run needs an end: seconds or episodes")
        if self.secure and self.insecure:
            raise ValueError("secure and insecure contradict each other: pass one of --secure, --insecure")
        if self.site is not None and not self.secure:
            raise ValueError("--site: a site's identities are for a secure fleet (fix: add --secure)")
        if self.site is not None:
            from hammer.protocol.identity import site_ca

            site_ca(self.site)  # before anything is written: one line naming `hammer site init`


# The plan's bounds, also settable as `--runtime FIELD=VALUE` on `hammer serve --realtime`.
PLAN_BOUNDS = ("hold_s", "missing_after_s", "max_msg_age_s", "max_absence_s", "msg_wait_s", "site_hold_s")
# The RuntimeSettings items every process of a fleet takes (each role's and robot's own link).
LINK_FIELDS = ("zenoh_lease_s", "zenoh_open_timeout_s", "reconnect_max_s")


def apply_runtime(plan: FleetPlan, items: list[str]) -> FleetPlan:
    """`--runtime FIELD=VALUE` items for a fleet (read by `runtime.settings.runtime_items`, the one
    parser): the plan's bounds (PLAN_BOUNDS) set on the plan, the rest kept as RuntimeSettings fields
    (checked when the fleet's runtime.json is made). ValueError naming the item on a bad one."""
    values = runtime_items(items)
    for key in PLAN_BOUNDS:
        if key in values:
            v = values.pop(key)
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise ValueError(f"--runtime {key}={v}: {key} takes seconds, e.g. {key}=0.5")
            setattr(plan, key, float(v))
    plan.runtime = values
    return plan


def link_items(plan: FleetPlan) -> list[str]:
    """The plan's `--runtime` items every role and robot gets (LINK_FIELDS)."""
    return [f"{key}={v}" for key, v in plan.runtime.items() if key in LINK_FIELDS]


def robot_endpoint(plan: FleetPlan) -> str:
    """Where a robot on another machine connects: the first `--listen` endpoint (an any-address one
    as `<this host>`), else the router's loopback endpoint (a robot on this machine). The plan's
    hub_port must be fixed (run_fleet fixes it before anything is printed or written)."""
    if plan.listen:
        proto, addr = plan.listen[0].split("/", 1)
        host, _, port = addr.rpartition(":")
        if host.strip("[]") in ("0.0.0.0", "::"):
            host = "<this host>"
        return f"{proto}/{host}:{port}"
    return loopback_endpoint(plan.hub_port)


def robot_command(plan: FleetPlan, i: int, run_dir: Path) -> str:
    """The exact command robot i runs (printed while the launcher waits for it, and in fleet.json):
    the router's real endpoint, its identity files in a secure fleet (on another machine, a copy of
    RUN/identity/{ca.pem,local-i.pem,local-i.key}), --insecure where a plain fleet reaches past loopback."""
    from hammer.protocol.identity import identity_dir
    from hammer.protocol.session import is_loopback_endpoint

    where = robot_endpoint(plan)
    plain_out = not plan.secure and ("<" in where or not is_loopback_endpoint(where))
    return shlex.join(["hammer", *role_args("local", bundle=plan.bundle, agent=i, run_id=Path(run_dir).name,
                                            connect=where, identity=plan.secure and identity_dir(Path(run_dir)),
                                            insecure=plain_out, runtime=link_items(plan), seed=plan.seed,
                                            fleet=True)])


def role_specs(plan: FleetPlan, run_id: str, connect: str, n_agents: int, uses_central: bool,
               run_dir: Path) -> list[RoleSpec]:
    """Each role's command, a Zenoh client of the router at `connect`; in a secure fleet each reads
    its own identity from RUN/identity/ (a role on another machine gets a copy of its three files)
    and makes `connect` a TLS endpoint."""
    from hammer.protocol.identity import identity_dir

    common = {"bundle": plan.bundle, "run_id": run_id, "connect": connect,
              "identity": plan.secure and identity_dir(run_dir), "seed": plan.seed, "runtime": link_items(plan)}
    specs = [RoleSpec("env", role_args("fleet-world", **common, hz=plan.hz, hold_s=plan.hold_s, msg_wait_s=plan.msg_wait_s,
                                       run_dir=run_dir, no_site_feed=plan.site_external,
                                       timeline=plan.timeline, seconds=plan.seconds, episodes=plan.episodes)),
             RoleSpec(POLICY, role_args("fleet-policy", **common, run_dir=run_dir), restart=True, essential=False)]
    if uses_central:
        specs.append(RoleSpec("central", role_args("fleet-central", **common, hz=plan.hz,
                                                   missing_after_s=plan.missing_after_s, site_hold_s=plan.site_hold_s),
                              restart=True, essential=False))
    for i in range(n_agents):
        if i in plan.external:
            continue
        specs.append(RoleSpec(f"local-{i}", role_args("local", **common, agent=i, fleet=True,
                                                      max_msg_age_s=plan.max_msg_age_s),
                              restart=True, essential=False))
    return specs


# What one fleet session leaves as its results; a new session in the same directory serves the bundle
# given, so an earlier session's update history must not be followed again (deploy/launcher.py, SERVED_RESULTS).
SESSION_RESULTS = ("summary.json", "world.json", "pushes.json", "policies")


def _set_aside(run_dir: Path) -> Path | None:
    """Move an earlier session's results to RUN/previous/<time>/ (None: there were none)."""
    from hammer.deploy.launcher import move_to_previous

    return move_to_previous(run_dir, SESSION_RESULTS, "fleet")


def fleet_settings(b, plan: FleetPlan, run_id: str):
    """The fleet's RuntimeSettings (its runtime.json): eval mode, the plan's `--runtime` items, the
    router's real port and `--listen` endpoints; a secure fleet has the router's `hub` identity.
    ValueError naming the field on a bad item."""
    from hammer.serve.served_settings import serve_settings

    fixed = {**plan.runtime, **({"secure": True, "secure_hub": True} if plan.secure else {}),
             **({"insecure": True} if plan.insecure else {}), "hub_port": plan.hub_port,
             "max_absence_s": plan.max_absence_s}
    settings, _ = serve_settings(b, run_id, listen=plan.listen, fixed=fixed)
    return settings


def write_served_files(b, plan: FleetPlan, run_dir: Path, settings) -> None:
    """runtime.json (`settings`, the bundle as policy version 0), config.json (the team at K = 1) and
    env_spec.json: the files `hammer push` / `hammer rollback` (serve/push.py) check a push against
    and the policy server reads, the same as a lock-stepped `hammer serve` writes."""
    from hammer.runtime.settings import write_env_spec

    # absolute: `hammer push` / `hammer rollback` may run from another directory than the launcher
    settings = replace(settings, policy_dir=str(Path(b.policy_dir).resolve()))
    settings.save(run_dir)
    cfg = b.config(num_envs=1, **({} if plan.seed is None else {"seed": plan.seed}))
    (run_dir / "config.json").write_text(json.dumps(cfg.model_dump(mode="json"), indent=1))
    write_env_spec(run_dir, b.env_spec())


def run_fleet(plan: FleetPlan, run_dir: Path, on_tick=None) -> dict:
    """Run the fleet until the world is done; returns (and writes) RUN/summary.json."""
    from hammer.faults.chaos import ChaosScheduler
    from hammer.serve.bundle import load_bundle
    from hammer.serve.edge_agent import fleet_check, site_columns

    plan.check()
    b = load_bundle(plan.bundle)
    fleet_check(b)
    site_feed = b.wiring().uses_central and site_columns(b.env_spec_data) is not None
    chaos = ChaosScheduler.from_strings(plan.chaos) if plan.chaos else None
    n = int(b.env_spec_data["n_agents"])
    if any(not 0 <= i < n for i in plan.external):
        raise ValueError(f"external robots {plan.external}: this team has robots 0..{n - 1}")
    plan.hub_port = plan.hub_port or free_loopback_port()
    connect = loopback_endpoint(plan.hub_port)
    run_dir = Path(run_dir)
    run_id = run_dir.name
    settings = fleet_settings(b, plan, run_id)
    hub_transport = settings.link(TransportConfig(mode="router", listen=[connect, *plan.listen]), fleet=True)
    refuse_plain_beyond_loopback(hub_transport, plan.secure, plan.insecure)
    run_dir.mkdir(parents=True, exist_ok=True)
    _set_aside(run_dir)
    write_served_files(b, plan, run_dir, settings)
    if plan.secure:
        from hammer.deploy.launcher import secure_identities

        hub_transport = secure_identities(n, settings, run_dir, hub_transport, fresh=True, site=plan.site,
                                          as_role=HUB, site_feed=site_feed)
    specs = role_specs(plan, run_id, connect, n, b.wiring().uses_central, run_dir)
    if chaos is not None:
        chaos.validate_roles({s.name for s in specs})
    robots = {f"local-{i}": robot_command(plan, i, run_dir) for i in plan.external}
    fleet_json = json.dumps({
        "bundle": str(plan.bundle), "run_id": run_id, "hub": hub_transport.listen[0],
        "endpoint": robot_endpoint(plan), "plan": {**plan.__dict__, "bundle": str(plan.bundle),
                                                  "timeline": plan.timeline and str(plan.timeline),
                                                  "site": plan.site and str(plan.site)},
        "commands": {s.name: "hammer " + shlex.join(s.args) for s in specs},
        "robot_commands": robots}, indent=1)
    board = FleetBoard()
    t0 = time.monotonic()

    def started_world(sup, board) -> None:  # chaos's clock (t=...) starts with the world's
        world = board.heartbeats.get("env")
        if world is not None and world.counters.get("ticks", 0) > 0:
            chaos(sup, board)

    # The one launcher loop (deploy/launcher.py), as a fleet runs it: no waiting for anyone to be up (robots
    # join when they can; the world waits for them), robots that keep dying are let go (the verdict
    # names their absence), on a fleet's clock.
    launcher = Launcher(specs, run_dir, settings.startup_timeout_s,
                        on_tick=None if on_tick is None else (lambda board: on_tick(board, time.monotonic() - t0)),
                        chaos=None if chaos is None else started_world, settings=settings,
                        external=robots, wait_alive=False, watch_liveliness=False, board=board, tick_s=0.1, stop_wait_s=5.0,
                        heard=lambda h: _note_version(board, h, time.monotonic() - t0))
    stopped_by = None
    if plan.secure:  # strangers turned away at the hub's TLS handshake: counted for the verdict (a plain hub has no handshake to refuse)
        watch_refused()
    # SIGTERM (a service manager's stop) and Ctrl-C end a fleet as they end a served run: every role
    # stopped, summary.json written with `"interrupted": true, "stopped_by": "SIGTERM"` (or "SIGINT")
    with stop_on_signals((signal.SIGTERM, signal.SIGINT)) as state:
        launcher.stopping = state  # marked ending once the launcher broadcasts the stop
        try:
            with HammerSession(run_id, hub_transport, sender=LAUNCHER) as hub:
                (run_dir / "fleet.json").write_text(fleet_json)  # once the router listens: a client may join now
                launcher.run(hub)
        except UpError as e:  # the world failed: every role was stopped all the same
            stopped_by = str(e)
        except KeyboardInterrupt as e:  # Stopped by a signal stop_on_signals took; a bare one is Ctrl-C's
            stopped_by = getattr(e, "signal_name", "SIGINT")
        finally:
            state["ending"] = True  # a repeated signal must not cut the summary short
    return _summary(run_dir, board, stopped_by, time.monotonic() - t0, plan.max_absence_s, site_feed)


@dataclass
class FleetBoard(Board):
    """The launcher's board with what a fleet adds: each robot's and the central agent's policy
    version, and every switch seen (summary.json: `version_switches`)."""

    versions: dict[str, int] = field(default_factory=dict)
    switches: dict[str, list[dict]] = field(default_factory=dict)


def _note_version(board, h: Heartbeat, t: float) -> None:
    """A robot's or the central agent's `policy_version` gauge changed: a switch, kept by name."""
    if not (h.role.startswith("local-") or h.role == "central") or "policy_version" not in h.gauges:
        return
    v, before = int(h.gauges["policy_version"]), board.versions.get(h.role)
    board.versions[h.role] = v
    if before is not None and v != before:
        board.switches.setdefault(h.role, []).append({"t_s": round(t, 2), "from": before, "to": v})
        log.info("%s acts with policy version %d (was %d)", h.role, v, before)


def _summary(run_dir: Path, board, stopped_by: str | None, wall_s: float, max_absence_s: float,
             site_feed: bool = False) -> dict:
    """summary.json: the world's figures per robot with what each robot said of itself, and the
    outages by name (a robot missing longer than `max_absence_s` makes the run degraded, named)."""
    world_file = run_dir / "world.json"
    world = json.loads(world_file.read_text()) if world_file.is_file() else {}
    roles = {name: {"counters": dict(h.counters), "gauges": dict(h.gauges)} for name, h in board.heartbeats.items()}
    robots = world.get("robots", {})
    for name, r in robots.items():
        edge = roles.get(name, {})
        r.update({k: edge.get("counters", {}).get(k) for k in ("acts", "msg_fresh", "msg_stale", "msg_none")})
        r.update({k: edge.get("gauges", {}).get(k) for k in ("msg_age_p50_ms", "msg_age_p99_ms", "policy_version",
                                                               "policy_held")})
        r.update({k: edge.get("counters", {}).get(k) for k in ("policy_switches", "versions_pulled", "chunk_queries",
                                                                 "chunks_refused", "weights_rejected")})
        r["version_switches"] = board.switches.get(name, [])
    absences = world.get("absences", {})
    verdict = fleet_verdict(list(robots) or sorted(absences), absences, world, roles, max_absence_s, refused_counts(),
                            site_feed=site_feed)
    summary = {"completed": stopped_by is None and bool(world), "interrupted": stopped_by in ("SIGTERM", "SIGINT"),
               "stopped_by": stopped_by, "wall_s": round(wall_s, 3),
               "degraded": bool(verdict["reasons"]), "degraded_reasons": verdict["reasons"], "absences": absences,
               "central_absences": verdict["central_absences"], "rejections": verdict["rejections"],
               "rejected_on": verdict["rejected_on"], "refused_connections": verdict["refused_connections"],
               "world": {k: v for k, v in world.items() if k != "robots"}, "robots": robots,
               "central": {**roles.get("central", {}).get("counters", {}),
                           **{k: v for k, v in roles.get("central", {}).get("gauges", {}).items()
                              if k.startswith("policy_")},
                           "version_switches": board.switches.get("central", [])},
               "site": verdict["site"],
               "policy_server": {**roles.get(POLICY, {}).get("counters", {}),
                                 **roles.get(POLICY, {}).get("gauges", {})},
               "pushes": _pushes(run_dir),
               "restarts": board.restarts, "chaos": board.chaos_log}
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def _pushes(run_dir: Path) -> list[dict]:
    """The session's update history, in short: each entry's version, action and time."""
    from hammer.runtime.pushes import HistoryError, read_pushes

    try:
        return [{k: e.get(k) for k in ("version", "action", "restores_version", "at") if k in e}
                for e in read_pushes(run_dir)]
    except HistoryError as e:
        return [{"error": str(e)}]
