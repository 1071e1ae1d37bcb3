"""`hammer up`: one experiment as separate processes on one host.

The launcher writes the run directory (config.json, runtime.json, env_spec.json), opens the hub
Zenoh session every role connects to, starts each role as a fresh interpreter, waits until every
role's liveliness token is up, shows a live dashboard from the roles' heartbeats, restarts local
agents and the central agent if they die, and stops everything at the end of the budget or on
Ctrl-C. A role that cannot be kept alive ends the run with a one-line reason (a learner that
dies: its last log lines and the `hammer up --resume` command). A run that completes with too
many default actions, fallback messages or rejected messages is marked degraded in summary.json
(`degraded`, `degraded_reasons`; thresholds in RuntimeSettings), not silently "completed".

`launch(..., resume=True)` continues a run directory whose session died (`hammer up --resume`):
see `prepare_resume` and docs/runtime.md ("Resuming a run").
"""

from __future__ import annotations

import json
import logging
import os
import re
import secrets
import shlex
import time
from dataclasses import dataclass, field
from pathlib import Path

from hammer.deploy.attendance import Attendance
from hammer.deploy.supervisor import RoleSpec, Supervisor, role_args
from hammer.protocol.access import LAUNCHER
from hammer.protocol.schemas import Control, Heartbeat
from hammer.protocol.session import HammerSession, free_loopback_port
from hammer.protocol.structs import replace
from hammer.runtime.bounds import RUN_STEP_ENV, RUN_VERSION_ENV
from hammer.runtime.heartbeats import HeartbeatLedger
from hammer.runtime.process import Stopped, on_signals
from hammer.runtime.role import rejection_counters
from hammer.runtime.settings import RuntimeSettings, write_env_spec

log = logging.getLogger("hammer.up")


class UpError(RuntimeError):
    """The run could not complete; the message is the one-line reason."""


@dataclass
class UpResult:
    run_dir: Path
    summary: dict
    restarts: dict[str, int]
    wall_time: float
    links: dict[str, dict[str, int]] = field(default_factory=dict)  # per-link counters (faults.links)
    chaos_log: list[dict] = field(default_factory=list)
    stopped_by: str | None = None  # the signal that stopped the run before its budget (launch's stop_signals)


@dataclass
class Board:
    """What the dashboard shows, from heartbeats and the supervisor."""

    heartbeats: dict[str, Heartbeat] = field(default_factory=dict)
    alive: set[str] = field(default_factory=set)
    restarts: dict[str, int] = field(default_factory=dict)
    steps_hist: list[tuple[float, int]] = field(default_factory=list)
    held: set[str] = field(default_factory=set)  # killed by chaos: not restarted automatically
    chaos_log: list[dict] = field(default_factory=list)
    last_by_pid: dict[tuple[str, int], dict] = field(default_factory=dict)  # last heartbeat counters per process
    attendance: Attendance | None = None  # every role's token going and coming back (deploy.attendance)

    def env_rate(self) -> float:
        if len(self.steps_hist) < 2:
            return 0.0
        (t0, s0), (t1, s1) = self.steps_hist[0], self.steps_hist[-1]
        return (s1 - s0) / max(t1 - t0, 1e-9)


def role_specs(cfg, run_dir: Path, settings: RuntimeSettings | None = None) -> list[RoleSpec]:
    """Every process `hammer up` starts. Local agents: one process each, or agent pools of
    `settings.agents_per_process` agents (`hammer local --agents`), one process and one event loop
    each; a pool's `members` are the liveliness names of its agents. The weights come from the
    learner, or in a served run from the policy server (role `policy`, the same command)."""
    from hammer.protocol.access import pool_name

    settings_or_default = settings or RuntimeSettings(run_id="-")
    specs = [RoleSpec(settings_or_default.policy_role, role_args("learner", run_dir=run_dir))]
    if cfg.wiring.uses_central:
        specs.append(RoleSpec("central", role_args("central", run_dir=run_dir), restart=True))
    groups = settings_or_default.agent_groups(cfg.n_agents)
    external = {int(e.split("-")[1]) for e in (settings.external if settings else ()) if re.fullmatch(r"local-\d+", e)}
    for i in sorted(external):
        groups.append([i])
    for g in sorted(groups):
        if len(g) == 1:
            specs.append(RoleSpec(f"local-{g[0]}", role_args("local", run_dir=run_dir, agent=g[0]), restart=True))
        else:
            specs.append(RoleSpec(pool_name(g), role_args("local", run_dir=run_dir, agents=",".join(map(str, g))),
                                  restart=True,
                                  members=tuple(f"local-{i}" for i in g)))
    specs.append(RoleSpec("env", role_args("env-host", run_dir=run_dir)))
    return specs


def resolve_agents_per_process(cfg, settings: RuntimeSettings) -> RuntimeSettings:
    """`agents_per_process=0` (the default) becomes the machine's choice (auto_agents_per_process),
    written into runtime.json so every role of the run (and its access rules) agrees on the pools."""
    from hammer.runtime.settings import auto_agents_per_process

    if settings.agents_per_process:
        return settings
    return replace(settings, agents_per_process=auto_agents_per_process(cfg.n_agents))


def external_commands(cfg, run_dir: Path, external: list[str], settings: RuntimeSettings | None = None) -> dict[str, str]:
    """The command that starts each role `hammer up --external NAME` leaves to the user (its log
    going where the launcher would put it, so the run directory is the same)."""
    specs = {s.name: s for s in role_specs(cfg, run_dir, settings)}
    unknown = [n for n in external if n not in specs]
    if unknown:
        raise UpError(f"--external {', '.join(unknown)}: not a role of this run; fix: use one of {', '.join(specs)}")
    logs = Path(run_dir) / "logs"
    return {n: f"hammer {shlex.join(specs[n].args)} 2>> {shlex.quote(str(logs / f'{n}.log'))}" for n in external}


# What a session leaves besides the learning results; an earlier attempt's copies must not mix
# into a fresh run started in the same directory (RunDir.create accepts a dir without checkpoint).
SESSION_LEFTOVERS = ("host_state", "linksteps", "counters")


def prepare_run_dir(cfg, settings: RuntimeSettings, run_dir: Path) -> None:
    import shutil

    from hammer.envs.registry import make_vec_env
    from hammer.learning.config import ConfigError
    from hammer.learning.run_env import check_env_fits
    from hammer.learning.rundir import RunDir

    env = make_vec_env(cfg.env, cfg.n_agents, 1, env_kwargs=cfg.env_kwargs or None, adapters=cfg.env_adapters)
    spec = env.spec
    env.close()
    check_env_fits(cfg, spec)  # a config asking more of the env than it gives: refused before any file is written
    try:
        rd = RunDir.create(run_dir, cfg)
    except ConfigError as e:
        raise UpError(str(e)) from None
    rd.close()
    for name in SESSION_LEFTOVERS:
        shutil.rmtree(run_dir / name, ignore_errors=True)
    for name in ("env_summary.json", "learner_summary.json", "episode_links.csv", "links.json"):
        (run_dir / name).unlink(missing_ok=True)
    settings.save(run_dir)
    write_env_spec(run_dir, spec)


# What one served session leaves as its results (the logs are appended to); a served run has nothing to
# resume, so serving again in the same directory (a restarted service keeps its run id) starts afresh.
SERVED_RESULTS = ("summary.json", "env_summary.json", "metrics.csv", "links.json", "episode_links.csv", "trace.npz",
                  "pushes.json", "policies")


def set_aside_served_session(run_dir: Path) -> Path | None:
    """Move an earlier served session's results (its pushes included: a new session serves the bundle
    given) to RUN/previous/<time>/, so `hammer serve --run-dir` of the same directory can start again
    with the same run id (edge agents waiting with `--stay` join it). A training run's directory is
    left alone (RunDir.create refuses it as before). `hammer serve` calls it; `launch` itself still
    refuses a directory that holds a run, for every other caller. Returns where they went, or None."""
    run_dir = Path(run_dir)
    rt = run_dir / "runtime.json"
    try:
        served = json.loads(rt.read_text()).get("mode") == "eval"
    except (OSError, ValueError):
        return None
    if not served or not (run_dir / "summary.json").exists():
        return None
    return move_to_previous(run_dir, SERVED_RESULTS, "served")


def move_to_previous(run_dir: Path, names: tuple[str, ...], what: str) -> Path | None:
    """Move those of `names` that RUN holds to RUN/previous/<time>/ (None: it held none of them):
    a served run's or a fleet's earlier session, kept rather than overwritten."""
    present = [run_dir / n for n in names if (run_dir / n).exists()]
    if not present:
        return None
    dest = run_dir / "previous" / time.strftime("%Y%m%d-%H%M%S")
    while dest.exists():
        dest = dest.with_name(dest.name + "x")
    dest.mkdir(parents=True)
    for p in present:
        p.rename(dest / p.name)
    log.info("the previous %s session's results are in %s", what, dest)
    return dest


def resume_point(run_dir: Path) -> int:
    """The latest update with both a learner checkpoint and the env host's state. The two are
    written at the same points (every checkpoint_every updates) by different processes, so a kill
    between them leaves one without the other."""
    from hammer.env_host.checkpoint import host_state_updates

    ckpt_dir = Path(run_dir) / "checkpoints"
    learner = {int(p.stem[5:]) for p in ckpt_dir.glob("ckpt_*.json")} if ckpt_dir.is_dir() else set()
    both = learner & set(host_state_updates(run_dir))
    if not both:
        raise UpError(f"{run_dir} has no checkpoint yet; start it again (hammer up --run-dir {run_dir})")
    return max(both)


def prepare_resume(cfg, settings: RuntimeSettings, run_dir: Path) -> RuntimeSettings:
    """Make `run_dir` ready to continue at its resume point U; returns the new session's settings.

    Keeps every file; drops only what lies beyond U (learner checkpoints and host states of later
    updates, the run's summaries), so the new session rewrites it. The new session gets a fresh
    run id (no message of a killed session's surviving process can mix in), a fresh hub port, and
    a step counter above any step the killed session can have reached: at most checkpoint_every x
    rollout_steps vector steps after its latest host state (an env host writes one at every
    checkpoint point, including the one it resumes from, before stepping)."""
    from hammer.env_host.checkpoint import host_state_updates, read_host_state
    from hammer.faults.chaos import parse_chaos
    from hammer.faults.steplog import STEP_LOG_DIR
    from hammer.learning.rundir import RunDir

    if settings.mode != "train":
        raise UpError(f"{run_dir}: only a training run can be resumed (runtime.json has mode={settings.mode})")
    done = run_dir / "summary.json"
    # Complete = the env host spent the budget AND the learner exported final/ (it writes its
    # summary last); a session killed between the two is resumed like any other.
    if done.is_file() and (run_dir / "learner_summary.json").is_file():
        have = int(json.loads(done.read_text()).get("episodes", 0))
        if have >= cfg.episodes:
            raise UpError(f"{run_dir} is already complete ({have} episodes); fix: pass a larger --episodes "
                          "to continue it")
    u = resume_point(run_dir)
    state = read_host_state(run_dir, u)
    if state["episodes"] >= cfg.episodes:
        raise UpError(f"--episodes {cfg.episodes}: the checkpoint of update {u} already has {state['episodes']} "
                      "episodes; fix: pass a larger --episodes")
    step = max(int(read_host_state(run_dir, v)["step"]) for v in host_state_updates(run_dir))
    step += cfg.checkpoint_every * cfg.rollout_steps
    rd = RunDir(run_dir)
    for v in host_state_updates(run_dir):
        if v > u:
            (run_dir / "host_state" / f"ckpt_{v:07d}.json").unlink()
    for p in rd.ckpt_dir.glob("ckpt_*"):
        if int(p.name[5:12]) > u:
            p.unlink()
    for name in ("summary.json", "env_summary.json", "learner_summary.json"):
        (run_dir / name).unlink(missing_ok=True)
    # Step logs are named <role>-<pid>.csv and opened for writing: a new process that got an old
    # pid would truncate the earlier session's log, so those are renamed (readers take every *.csv).
    tag = time.strftime("%Y%m%d%H%M%S")
    for p in sorted((run_dir / STEP_LOG_DIR).glob("*.csv")):
        p.rename(p.with_name(f"s{tag}-{p.name}"))
    rd.write_config(cfg)  # --episodes may have changed
    # Chaos events at a step the run has passed already happened (or were lost with the session).
    chaos = [c for c in settings.chaos if (ev := parse_chaos(c)).at_step is None or ev.at_step > step]
    base = re.sub(r"-r\d+-[0-9a-f]{6}$", "", settings.run_id)[:50]
    new = replace(settings, run_id=f"{base}-r{u}-{secrets.token_hex(3)}", resume_from=u, resume_step=step, chaos=chaos,
                  hub_port=0 if not settings.zenoh_config_file else settings.hub_port)
    log.info("resuming %s at update %d (%d episodes), step counter from %d", run_dir, u, state["episodes"], step + 1)
    return new


def _launcher_log(run_dir: Path, max_mb: float) -> logging.Handler:
    """RUN/logs/launcher.log: the launcher's warnings and every role's leaves and rejoins
    (deploy.attendance), which otherwise only scroll past on a terminal; rotated as the roles' logs
    are (runtime.process), so a run of days keeps at most three files of `max_mb`."""
    from logging.handlers import RotatingFileHandler

    (run_dir / "logs").mkdir(parents=True, exist_ok=True)
    h = RotatingFileHandler(run_dir / "logs" / "launcher.log", maxBytes=max(1, int(max_mb * 2**20)), backupCount=2)
    h.setFormatter(logging.Formatter("%(asctime)s launcher %(levelname)s %(name)s: %(message)s"))
    logging.getLogger("hammer.up").addHandler(h)
    own = logging.getLogger(FILE_ONLY)  # the launcher's own start and stop lines: the file, not the console
    own.propagate, own.level = False, logging.INFO
    own.addHandler(h)
    return h


FILE_ONLY = "hammer.up.launcher"


def _tail(path: Path, lines: int = 3) -> str:
    try:
        text = path.read_text(errors="replace").strip().splitlines()
    except FileNotFoundError:
        return ""
    return " | ".join(text[-lines:])


def launch(cfg, settings: RuntimeSettings, run_dir: Path, on_tick=None, chaos=None, resume: bool = False,
           external_agents: tuple[int, ...] = (), external_help: dict[str, str] | None = None,
           stop_signals: tuple[int, ...] = (), stop=None) -> UpResult:
    """Run one distributed experiment to its budget. `on_tick(board)` is called ~4 times a second;
    `chaos(sup, board)` may kill/pause roles (fault experiments and tests); without it,
    `settings.chaos` (e.g. 'kill:central@step=200') is scheduled by `faults.chaos.ChaosScheduler`.
    `resume=True`: continue `run_dir` (its config.json / runtime.json as `cfg` / `settings`) from
    its latest checkpoint instead of starting a new run. `external_agents`: local agents joining from
    elsewhere (`hammer serve --external-agent`; as `settings.external`: not launched, awaited).
    `external_help`: the command to show for an external role instead of `hammer <role> --run-dir`
    (`hammer serve` shows the bundle's edge command). `stop_signals` (main thread only): signals that
    stop the run as Ctrl-C does and then return what ran (`UpResult.stopped_by`; a served run's
    summary.json says `interrupted`), so a service manager's stop is a clean end, not a failure.
    `stop()` (any thread): asked every launcher tick, startup included; a signal name returned stops
    the run as that signal would (a launch in a worker thread, where signals cannot reach it: the
    runs of `hammer faults sweep`); before anything started it raises Stopped."""
    run_dir = Path(run_dir)
    if stop is not None and (by := stop()):
        raise Stopped(by)
    with stop_on_signals(stop_signals) as stopping:
        return _launch(cfg, settings, run_dir, on_tick, chaos, resume, external_agents, external_help or {},
                       stopping, stop)


def _stop_every_role(name: str) -> None:
    log.warning("%s: stopping every role", name)
    raise Stopped(name)


def stop_on_signals(signals: tuple[int, ...]):
    """While launching (runtime.process.on_signals, the one policy): the first of `signals` raises
    Stopped (the launcher's stop broadcast to every role, external ones included, follows as after
    Ctrl-C, and then what ran is written instead of a failure); later ones, and any once the run is
    ending (`state["ending"]`), are logged and ignored."""
    return on_signals(signals, _stop_every_role)


def _launch(cfg, settings: RuntimeSettings, run_dir: Path, on_tick, chaos, resume: bool,
            external_agents: tuple[int, ...], external_help: dict[str, str], stopping: dict, stop=None) -> UpResult:
    if resume:
        settings = prepare_resume(cfg, settings, run_dir)
    if external_agents:
        settings = replace(settings, external=[*settings.external, *(
            f"local-{i}" for i in external_agents if f"local-{i}" not in settings.external)])
    if not resume:
        settings = resolve_agents_per_process(cfg, settings)
    specs = role_specs(cfg, run_dir, settings)
    external = external_commands(cfg, run_dir, settings.external, settings)
    external.update({k: v for k, v in external_help.items() if k in external})
    if chaos is None and settings.chaos:
        from hammer.faults.chaos import ChaosScheduler

        chaos = ChaosScheduler.from_strings(settings.chaos)
        chaos.bind_pools(specs)
        chaos.validate_roles({s.name for s in specs})
    if settings.hub_port == 0 and not settings.zenoh_config_file:
        settings = replace(settings, hub_port=free_loopback_port())
    if resume:
        settings.save(run_dir)
    else:
        prepare_run_dir(cfg, settings, run_dir)
    hub_transport = settings.hub_transport()
    try:
        settings.refuse_plain_beyond_loopback(hub_transport)
    except ValueError as e:
        raise UpError(str(e)) from None
    if settings.secure:
        hub_transport = secure_identities(cfg.n_agents, settings, run_dir, hub_transport, fresh=not resume)
    launcher = Launcher(specs, run_dir, settings.startup_timeout_s, on_tick, chaos, external, settings, stop,
                        stopping=stopping)
    stopped_by = None
    try:
        with HammerSession(settings.run_id, hub_transport, sender=LAUNCHER) as hub:
            launcher.run(hub)
    except Stopped as e:  # every role was told to stop (Launcher.run's stop_all): write what ran
        stopped_by = e.signal_name
    finally:
        stopping["ending"] = True
    summary_file = run_dir / "env_summary.json"
    summary = json.loads(summary_file.read_text()) if summary_file.is_file() else {}
    links, roles = _write_links(cfg, run_dir, launcher.board, launcher.own_rejections)
    _write_episode_links(run_dir, list(links))
    if stopped_by is not None:
        summary = _stopped_summary(cfg, settings, run_dir, summary, stopped_by)
    elif not summary.get("completed"):
        raise UpError(f"env host stopped before the budget was spent (see {run_dir / 'logs' / 'env.log'})")
    summary = _verdict(cfg, settings, run_dir, summary, links, roles, launcher.board.attendance)
    return UpResult(run_dir, summary, dict(launcher.board.restarts), time.monotonic() - launcher.t_start, links,
                    list(launcher.board.chaos_log), stopped_by)


def _stopped_summary(cfg, settings: RuntimeSettings, run_dir: Path, summary: dict, stopped_by: str) -> dict:
    """What a run stopped by a signal ran, marked `interrupted` and `stopped_by`. A served run gets its
    summary.json (its only result; a restarted `hammer serve` sets it aside). A training run does not:
    summary.json marks a run finished (sweeps skip it, the archive takes it), and this one continues
    with `hammer up --resume`; its env_summary.json says it."""
    summary = {"episodes": 0, "env_steps": 0, "final_paper_metric_last500": None, "n_agents": cfg.n_agents,
               "variant": cfg.variant, "env": cfg.env, **summary,
               "completed": False, "interrupted": True, "stopped_by": stopped_by}
    (run_dir / "env_summary.json").write_text(json.dumps(summary, indent=1))
    if settings.mode == "eval":
        from hammer.learning.rundir import RunDir

        RunDir(run_dir).write_summary(summary)
    log.warning("run stopped by %s after %d episodes", stopped_by, summary["episodes"])
    return summary


class Launcher:
    """The launcher role, the one launch-and-supervise loop of every launcher (`hammer up`, `hammer
    serve`, and with `wait_alive=False, watch_liveliness=False` a fleet's, deploy/fleet_launch.py): starts
    every role, waits for their liveliness, follows their heartbeats (`heard(h)`: each one believed),
    fires the chaos schedule, restarts the ones that may be restarted, and stops them all when the
    env host is done (or on any way out, Ctrl-C included). The only publisher of control commands.
    The caller writes the verdict from `board` once `run` returns."""

    tick_s = 0.25
    stop_wait_s = 10.0  # after the stop broadcast: how long roles get to exit on their own

    def __init__(self, specs: list[RoleSpec], run_dir: Path, startup_timeout_s: float, on_tick=None,
                 chaos=None, external: dict[str, str] | None = None, settings: RuntimeSettings | None = None,
                 stop=None, *, wait_alive: bool = True, watch_liveliness: bool = True, heard=None,
                 board: Board | None = None, tick_s: float | None = None, stop_wait_s: float | None = None,
                 stopping: dict | None = None) -> None:
        self.stop = stop  # launch's `stop`: asked every tick
        self.stopping = stopping  # the signal policy's state (stop_on_signals): marked ending at the stop broadcast
        # a fleet's roles and robots come and go while it runs: nothing waits for them to be up
        self.wait_for_alive, self.watch_liveliness, self.heard = wait_alive, watch_liveliness, heard
        self.tick_s = self.tick_s if tick_s is None else tick_s
        self.stop_wait_s = self.stop_wait_s if stop_wait_s is None else stop_wait_s
        self.specs, self.run_dir, self.startup_timeout_s = specs, run_dir, startup_timeout_s
        self.settings = settings or RuntimeSettings(run_id="-")
        self.on_tick, self.chaos = on_tick, chaos
        self.external = external or {}  # role -> the command that starts it by hand; never started here
        self.names = {s.name for s in specs}  # the processes
        self.alive_expected = {m for s in specs for m in (s.members or (s.name,))}  # their liveliness tokens
        self.sup = Supervisor(run_dir / "logs")
        self.sup.set_env(RUN_STEP_ENV, None)  # until the env host reports a step, the roles use runtime.json's
        self.sup.set_env(RUN_VERSION_ENV, None)  # ... and its resume version
        self.board = board if board is not None else Board()
        self.board.restarts = {n: 0 for n in self.names}
        self.board.attendance = Attendance(self.alive_expected) if watch_liveliness else None
        # Only counters the launcher can believe reach the verdict (runtime.heartbeats).
        self.ledger = HeartbeatLedger(self.sup.started_pids)
        self.own_rejections: dict[str, int] = {}  # the launcher's, as a role's final counters: rejected.<reason>
        self.t_start = time.monotonic()
        self.done = False

    def run(self, hub: HammerSession) -> None:
        self.watch = hub.watch_alive() if self.watch_liveliness else None
        self.heartbeats = hub.subscribe(hub.keys.heartbeat("*"), Heartbeat)
        # The env host's stop at the end of its budget: the tokens that go after it are roles stopping.
        # (A secure run keeps control to the launcher: there env_summary.json on disk says it, below.)
        self.stops = (None if self.settings.secure or not self.watch_liveliness
                      else hub.subscribe(hub.keys.ctl("all"), Control))
        file_log = _launcher_log(self.run_dir, self.settings.log_max_mb)
        own = logging.getLogger(FILE_ONLY)
        own.info("launcher started: run %s, pid %d, roles %s, run dir %s", self.settings.run_id, os.getpid(),
                 ", ".join(s.name for s in self.specs), self.run_dir)
        try:
            for name, cmd in self.external.items() if self.wait_for_alive else ():  # a fleet's command says it
                log.warning("external role %s: start it by hand with: %s", name, cmd)
            # A hand-started role must be subscribed before step 0: the env host then starts last.
            later = [s for s in self.specs if s.name == "env" and self.external and "env" not in self.external
                     and self.wait_for_alive]
            for spec in self.specs:
                if spec.name not in self.external and spec not in later:
                    self.sup.start(spec)
            if later:
                self.wait_alive(self.alive_expected - {"env"})
                self.sup.start(later[0])
            if self.wait_for_alive:
                self.wait_alive()
            if self.board.attendance is not None:
                self.board.attendance.start()
            while not self.done:
                self.tick()
        finally:
            if self.board.attendance is not None:
                self.board.attendance.end()
            self.stop_all(hub)
            own.info("launcher stopped: %s", "the env host is done" if self.done else "interrupted or failed")
            logging.getLogger("hammer.up").removeHandler(file_log)
            own.removeHandler(file_log)
            file_log.close()

    def wait_alive(self, names: set[str] | None = None) -> None:
        """Until every role's liveliness token is up; a role that exits meanwhile ends the run."""
        names = self.alive_expected if names is None else names
        deadline = time.monotonic() + self.startup_timeout_s
        while not names <= self.board.alive:
            self.check_stop()
            self.on_liveliness()
            for rp in self.sup.poll():
                raise UpError(f"role {rp.spec.name} exited with code {rp.exit_codes[-1]} during startup: "
                              f"{_tail(rp.log_path)} (log: {rp.log_path})")
            if time.monotonic() > deadline:
                missing = ", ".join(f"{n} (external: start it by hand)" if n in self.external else n
                                    for n in sorted(names - self.board.alive))
                raise UpError(f"roles not alive after {self.startup_timeout_s:.0f}s: {missing} "
                              f"(logs in {self.run_dir / 'logs'})")
            time.sleep(0.05)
        log.info("all %d roles alive after %.1fs", len(self.names), time.monotonic() - self.t_start)

    def check_stop(self) -> None:
        if self.stop is not None and (by := self.stop()):
            raise Stopped(by)

    def tick(self) -> None:
        self.check_stop()
        self.on_liveliness()
        for h in self.heartbeats.drain():
            self.on_heartbeat(h)
        if self.chaos is not None:
            self.chaos(self.sup, self.board)
        for rp in self.sup.poll():
            self.on_exit(rp)
        if self.on_tick is not None:
            self.on_tick(self.board)
        time.sleep(self.tick_s)

    def on_liveliness(self) -> None:
        att = self.board.attendance
        if self.watch is None:
            return
        if self.stops is not None and any(c.command == "stop" and c.sender in ("env", LAUNCHER)
                                          for c in self.stops.drain()):
            att.end()
        for ev in self.watch.drain():
            (self.board.alive.add if ev.alive else self.board.alive.discard)(ev.role)
            if ev.alive:
                att.up(ev.role)
            else:
                if (self.run_dir / "env_summary.json").is_file():  # the env host has finished: roles stop now
                    att.end()
                att.down(ev.role)
            if not ev.alive and ev.role == "env" and "env" in self.external:
                self.done = True  # a hand-started env host is gone: nothing of ours to wait for

    def on_heartbeat(self, h: Heartbeat) -> None:
        board = self.board
        if not self.ledger.offer(h):
            return
        board.heartbeats[h.role] = h
        board.last_by_pid[(h.role, h.pid)] = self.ledger.last[(h.role, h.pid)]
        if h.role == "env":
            # a role (re)started from now on refuses a first step beyond this + step_window (runtime.bounds)
            self.sup.set_env(RUN_STEP_ENV, str(max(0, int(h.counters.get("step", 0)))))
            # ... and first weights beyond this version + 1 + max_policy_lag
            self.sup.set_env(RUN_VERSION_ENV, str(max(0, int(h.gauges.get("policy_version", 0)))))
            board.steps_hist.append((time.monotonic(), int(h.counters.get("env_steps", 0))))
            board.steps_hist = board.steps_hist[-20:]
        if self.heard is not None:
            self.heard(h)

    def on_exit(self, rp) -> None:
        """A role process ended: the env host's clean exit ends the run; others are restarted if they may be."""
        name, code = rp.spec.name, rp.exit_codes[-1]
        if name == "env":
            if code != 0:
                raise UpError(f"env host exited with code {code}: {_tail(rp.log_path)} (log: {rp.log_path})")
            self.done = True
        elif code == 0:  # a clean exit: it was told to stop (the run is ending)
            return
        elif name in self.board.held:  # killed on purpose by the chaos schedule
            log.warning("role %s killed by chaos (code %s); held down: only a scheduled chaos restart (or for=) brings it back",
                        name, code)
        elif rp.spec.restart and rp.restarts < rp.spec.max_restarts:
            rp.restarts += 1
            self.board.restarts[name] = rp.restarts
            log.warning("role %s died (code %s); restart %d/%d", name, code, rp.restarts, rp.spec.max_restarts)
            self.sup.start(rp.spec)
        elif not rp.spec.essential:  # a fleet goes on without it (its verdict names the absence)
            log.warning("role %s died (code %s) %d times; going on without it", name, code, rp.restarts + 1)
        elif name == "learner":
            raise UpError(f"learner exited with code {code}: {_tail(rp.log_path, 5) or 'nothing in its log'} "
                          f"(log: {rp.log_path}); "
                          f"fix the cause, then continue from the last checkpoint: hammer up --resume {self.run_dir}")
        else:
            raise UpError(f"role {name} exited with code {code} and cannot be restarted: "
                          f"{_tail(rp.log_path)} (log: {rp.log_path})")

    def rejection_counters(self, hub: HammerSession) -> dict[str, int]:
        """What the launcher itself refused: malformed or mismatched heartbeats (its subscriptions)
        and heartbeats it could not believe (the ledger)."""
        return rejection_counters(hub.rejection_counts(), self.ledger.rejected)

    def stop_all(self, hub: HammerSession) -> None:
        """Tell every role to stop, give them `stop_wait_s` to exit cleanly, then end the rest."""
        if self.stopping is not None:
            self.stopping["ending"] = True  # a repeated signal must not cut the stop broadcast short
        try:
            hub.publish(hub.keys.ctl("all"), Control(command="stop"))
        except Exception as e:  # noqa: BLE001 - the hub may be closing; roles are stopped below anyway
            log.debug("could not broadcast stop: %s", e)
        deadline = time.monotonic() + self.stop_wait_s
        while ((any(self.sup.alive(n) for n in self.names) or self.externals_running())
               and time.monotonic() < deadline):
            self.sup.poll()
            self.take_last_heartbeats()
            time.sleep(0.1)
        self.sup.stop_all()
        self.take_last_heartbeats()
        self.own_rejections = self.rejection_counters(hub)

    def take_last_heartbeats(self) -> None:
        """The heartbeats that came while the roles stopped: each role's last (`stopped`) carries its
        final counters, all a role started elsewhere leaves the run directory (links.json)."""
        for h in self.heartbeats.drain():
            self.on_heartbeat(h)
        for ev in self.watch.drain() if self.watch is not None else ():
            (self.board.alive.add if ev.alive else self.board.alive.discard)(ev.role)

    def externals_running(self) -> bool:
        """A role started elsewhere that is still up (its token; without the liveliness watch: heard
        from) and has not sent its last heartbeat yet."""
        up = self.board.alive if self.watch is not None else self.board.heartbeats
        return any(n in up and getattr(self.board.heartbeats.get(n), "status", None) != "stopped"
                   for n in self.external)


def secure_identities(n_agents: int, settings: RuntimeSettings, run_dir: Path, hub_transport, fresh: bool,
                      site: Path | None = None, as_role: str | None = None, site_feed: bool = False):
    """A secure run (`hammer up`, `hammer serve`, a fleet): a new CA and role identities in
    RUN/identity/ (kept on resume, so remote roles keep the files they were given), and
    RUN/access_control.json, the rules every process applies (a client in another language inserts
    it into its Zenoh config; docs/wire-format.md). With `site` (a fleet's `--site`): the identities
    come from the site instead (protocol.identity: the robots' kept ones, the server roles' from its
    CA), so a restarted fleet admits the robots it admitted before. Returns the launcher's own
    secured transport, as `as_role` (default the launcher; a fleet's launcher is its router, `hub`).
    `site_feed`: a fleet whose team has a site feed also gets the `site` identity (its publisher)."""
    from hammer.protocol.access import LAUNCHER, access_control, role_names
    from hammer.protocol.identity import create_identities, has_identities, identity_dir, site_run_identities
    from hammer.protocol.keys import Keys

    roles = role_names(n_agents, pools=settings.pools(n_agents), router=settings.secure_hub, site_feed=site_feed,
                       served=settings.mode == "eval")
    if site is not None:
        site_run_identities(site, identity_dir(run_dir), roles)
    elif fresh or not has_identities(identity_dir(run_dir), roles):
        create_identities(identity_dir(run_dir), roles)
    rules = access_control(Keys(settings.run_id), n_agents, settings.pools(n_agents), router=settings.secure_hub)
    (run_dir / "access_control.json").write_text(json.dumps(rules, indent=1))
    return settings.secured(hub_transport, as_role or LAUNCHER, run_dir, n_agents)


def _write_links(cfg, run_dir: Path, board: Board, launcher_rejections: dict[str, int] | None = None):
    """links.json: per-link counters from every role's final counters (or last heartbeat), plus the
    chaos events that fired; the launcher's own rejections under `launcher`."""
    from hammer.faults.links import collect_role_counters, link_table

    roles = collect_role_counters(run_dir, board.last_by_pid)
    if launcher_rejections:
        roles[LAUNCHER] = {**roles.get(LAUNCHER, {}), **launcher_rejections}
    links = link_table(roles, cfg.n_agents, cfg.wiring.uses_central)
    (run_dir / "links.json").write_text(json.dumps({"links": links, "roles": roles, "chaos": board.chaos_log},
                                                   indent=1))
    return links, roles


def _verdict(cfg, settings: RuntimeSettings, run_dir: Path, summary: dict, links: dict, roles: dict,
             attendance: Attendance | None = None) -> dict:
    """summary.json (and env_summary.json) gain `degraded`, its reasons, the rejections per role and
    who was away when (`attendance`: a role away longer than max_absence_s degrades the run)."""
    from hammer.faults.links import degraded_reasons, rejections

    steps = int(roles.get("env", {}).get("step", 0)) - (settings.resume_step or 0)
    reasons = degraded_reasons(roles, links, max(steps, 0) * cfg.num_envs * cfg.n_agents,
                               settings.degraded_fraction, settings.degraded_rejections)
    extra = {}
    if attendance is not None:
        reasons += attendance.degraded_reasons(settings.max_absence_s)
        extra["attendance"] = attendance.summary()
    summary = {**summary, "degraded": bool(reasons), "degraded_reasons": reasons, "rejected": rejections(roles), **extra}
    for name in ("summary.json", "env_summary.json"):
        path = run_dir / name
        if path.is_file():
            path.write_text(json.dumps({**json.loads(path.read_text()), **{k: summary[k] for k in (
                "degraded", "degraded_reasons", "rejected", *extra)}}, indent=1))
    return summary


def _write_episode_links(run_dir: Path, links: list[str]) -> None:
    """episode_links.csv gets the per-episode link columns: the roles' step logs (RUN/linksteps)
    summed over each episode's steps (faults.episode_links). Every role has stopped by now."""
    from hammer.faults.episode_links import write_episode_links

    try:
        write_episode_links(run_dir, links, return_rows=False)
    except (OSError, ValueError) as e:  # the run's own results stand without the per-episode view
        log.warning("episode_links.csv: per-link columns not added: %s", e)
