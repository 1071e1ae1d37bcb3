"""`hammer up` and the role commands."""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path
from typing import Annotated

import typer

from hammer.commands.common import ConfigFieldsHelp, InsecureOpt, SecureOpt, fail
from hammer.commands.view import ViewOpt, ViewTokenOpt
from hammer.deploy.dashboard import dashboard_table, status_line


def register(app: typer.Typer) -> None:
    from hammer.commands import roles

    app.command("up", cls=ConfigFieldsHelp)(up_command)
    app.command("env-host")(roles.env_host_command)
    app.command("central")(roles.central_command)
    # `hammer local --bundle` is parsed by hammer/commands/edge.py alone (entry.py sends it there): its
    # options are listed in this command's help from that one definition
    app.command("local", epilog=roles.local_epilog())(roles.local_command)
    app.command("learner")(roles.learner_command)


def up_command(
    config_arg: Annotated[Path | None, typer.Argument(
        metavar="[CONFIG]", help="YAML file of RunConfig fields (the same as --config).")] = None,
    config: Annotated[Path | None, typer.Option(
        "--config", help="YAML file of RunConfig fields (as `hammer train --config`).")] = None,
    preset: Annotated[str | None, typer.Option(help="cn3 | cn5 | mw3 | mw5 (the paper's settings; default cn3), rware-tiny-2ag | rware-tiny-4ag.")] = None,
    variant: Annotated[str | None, typer.Option(help="hammer | il | random | centralized (default hammer).")] = None,
    central_mode: Annotated[str | None, typer.Option(help="rl (paper text) | backprop (authors' code).")] = None,
    seed: Annotated[int | None, typer.Option(help="Run seed.")] = None,
    episodes: Annotated[int | None, typer.Option(help="Episode budget (default: the preset's).")] = None,
    set_: Annotated[list[str] | None, typer.Option("--set", help="RunConfig field=value, repeatable.")] = None,
    runtime: Annotated[list[str] | None, typer.Option(
        "--runtime", help="RuntimeSettings field=value, repeatable, e.g. msg_deadline_ms=20, fallback=last.")] = None,
    faults: Annotated[Path | None, typer.Option(help="JSON/YAML FaultSpec file (seeded drop/delay/duplicate/reorder rules).")] = None,
    fault: Annotated[list[str] | None, typer.Option(
        "--fault", help="Link fault, repeatable: LINK:FIELD=VALUE,... with LINK env->central | env->local | "
                        "central->local | local->env, e.g. 'central->local:agent=1,drop=0.2,delay_ms=5,jitter_ms=2'.")] = None,
    fault_seed: Annotated[int | None, typer.Option(help="Seed of the link faults (same seed, same faults).")] = None,
    chaos: Annotated[list[str] | None, typer.Option(
        "--chaos", help="Process chaos, repeatable: ACTION:ROLE@step=N|t=S[,for=S] with ACTION kill | pause | "
                        "resume | restart, e.g. 'kill:central@step=2000' or 'pause:local-1@t=10s,for=3s'.")] = None,
    out: Annotated[str | None, typer.Option(help="Root directory for run directories (default runs).")] = None,
    run_dir: Annotated[Path | None, typer.Option(help="Exact run directory (default: OUT/up-<name>-<time>).")] = None,
    resume: Annotated[Path | None, typer.Option(
        help="Continue this `hammer up` run directory from its latest checkpoint (only --episodes may change).")] = None,
    dashboard: Annotated[bool, typer.Option(help="Live terminal dashboard (plain status lines when not a TTY).")] = True,
    external: Annotated[list[str] | None, typer.Option(
        "--external", help="Role started by hand instead (repeatable, e.g. local-2): the launcher prints its "
                           "command, waits for its liveliness and never restarts it; docs/wire-format.md.")] = None,
    secure: SecureOpt = False,
    insecure: InsecureOpt = False,
    view: ViewOpt = None,
    view_token: ViewTokenOpt = None,
) -> None:
    """Run a whole experiment as separate processes over Zenoh on this host.

    Starts the learner, the central agent (hammer/random), one client per local agent and the env
    host, each a fresh interpreter; waits until all are alive; trains to the episode budget;
    stops everything. Ctrl-C stops cleanly. Logs of every process are in RUN_DIR/logs/.

    The YAML file may also hold `faults:` ({seed, links: [...]} with link faults as mappings or
    --fault strings), `chaos:` (a list of --chaos strings) and `runtime:` (RuntimeSettings fields).
    Per-link counters end up in RUN_DIR/links.json, per-episode ones in RUN_DIR/episode_links.csv.

    `--resume RUN_DIR` continues a run whose session died (machine, Ctrl-C, kill) from the latest
    update with both a learner checkpoint and the env host's state (every checkpoint_every updates).
    """
    from rich.console import Console

    from hammer.deploy.plan import plan_up

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    console = Console(stderr=True)
    if config_arg is not None and config is not None:
        fail("a config file twice (CONFIG and --config); fix: pass one of them")
    config = config if config is not None else config_arg
    if resume is not None:
        given = {"--config": config, "--preset": preset, "--variant": variant, "--central-mode": central_mode,
                 "--seed": seed, "--set": set_, "--runtime": runtime, "--faults": faults, "--fault": fault,
                 "--fault-seed": fault_seed, "--chaos": chaos, "--out": out, "--run-dir": run_dir,
                 "--external": external, "--secure": secure or None, "--insecure": insecure or None}
        bad = [k for k, v in given.items() if v is not None]
        if bad:
            fail(f"--resume: only --episodes may be changed when resuming (got {', '.join(bad)}); "
                  "fix: drop the other options")
        cfg, settings = _resume_inputs(resume, episodes)
        run_up(cfg, settings, resume, dashboard, console, resume=True, view=view, view_token=view_token)
        return
    try:
        p = plan_up(config, preset=preset, set_=set_, runtime=runtime, faults_file=faults, fault=fault,
                    fault_seed=fault_seed, chaos=chaos, run_dir=run_dir, external=external, secure=secure,
                    insecure=insecure, fields={"variant": variant, "central_mode": central_mode, "seed": seed,
                                               "episodes": episodes, "out": out})
    except ValueError as e:  # ConfigError, FaultSpecError, ChaosSpecError, a bad --runtime item: one line
        fail(str(e))
    from hammer.protocol.structs import dump

    cfg, settings, path, plan = p.cfg, p.settings, p.run_dir, p.faults
    console.print(f"run dir: {path}")
    if plan.links:
        for lf in plan.links:
            console.print(f"fault: {lf.describe()} (seed {plan.seed})")
    elif settings.faults is not None and settings.faults.enabled:
        for r in settings.faults.rules:
            console.print(f"fault rule: {dump(r)}")
    for c in settings.chaos:
        console.print(f"chaos: {c}")
    run_up(cfg, settings, path, dashboard, console, view=view, view_token=view_token)


def _report_stopped(res, cfg, path: Path, served: bool) -> None:
    """The verdict of a run stopped by a signal, on stdout like a finished run's; a training run exits
    128 + the signal's number, with the command that continues it."""
    import signal

    from rich.console import Console

    s = res.summary
    metric = s.get("final_paper_metric_last500")
    Console(soft_wrap=True).print(
        f"stopped by {res.stopped_by}: {s.get('episodes', 0)} of {cfg.episodes} episodes in {res.wall_time:.0f}s, "
        f"paper metric {'-' if metric is None else f'{metric:.3f}'}; every role was stopped -> {path} "
        f"({'summary.json' if served else 'env_summary.json'})", markup=False)
    if not served:
        Console(stderr=True, soft_wrap=True).print(f"continue it with: hammer up --resume {path}", markup=False)
        raise typer.Exit(128 + signal.Signals[res.stopped_by].value)


def _resume_inputs(run_dir: Path, episodes: int | None):
    """config.json and runtime.json of a `hammer up` run directory (episodes possibly changed)."""
    import json

    from hammer.learning.config import ConfigError, build_config
    from hammer.runtime.settings import RuntimeSettings

    missing = [f for f in ("config.json", "runtime.json", "env_spec.json") if not (run_dir / f).is_file()]
    if missing:
        fail(f"--resume '{run_dir}': no {', '.join(missing)} there; fix: pass a run directory made by `hammer up` "
              "(a `hammer train` run continues with `hammer train --resume`)")
    try:
        cfg = build_config(json.loads((run_dir / "config.json").read_text()))
        if episodes is not None:
            cfg = build_config({**cfg.model_dump(), "episodes": episodes})
        settings = RuntimeSettings.load(run_dir)
    except ConfigError as e:
        fail(str(e))
    except Exception as e:  # noqa: BLE001 - a hand-edited runtime.json: say what is wrong in one line
        fail(f"--resume '{run_dir}': runtime.json: {' '.join(str(e).split())}")
    return cfg, settings


def _will_run(cfg, settings, path: Path, external_agents: tuple[int, ...]) -> str:
    """The line saying which processes this host starts (a served run has a policy server, no learner;
    agent pools are one process each)."""
    served = settings.mode == "eval"
    away = {*settings.external, *(f"local-{i}" for i in external_agents)}
    groups = [[i for i in g if f"local-{i}" not in away] for g in settings.agent_groups(cfg.n_agents)]
    local = [f"local-{g[0]}" if len(g) == 1 else f"local-{g[0]}..{g[-1]} ({len(g)} agents)" for g in groups if g]
    roles = [settings.policy_role, *(["central"] if cfg.wiring.uses_central else []), *local, "env"]
    here = [r for r in roles if r not in away]
    names = {"policy": "policy server", "central": "central agent", "env": "env host"}
    return (f"will run: {cfg.episodes:,} episodes as {len(here)} processes on this host "
            f"({', '.join(names.get(r, r) for r in here)}){' + external roles' if away else ''}; logs in {path}/logs; "
            "Ctrl-C stops" + ("" if served else f", `hammer up --resume {path}` continues from the last checkpoint"))


def run_up(cfg, settings, path: Path, dashboard: bool, console, resume: bool = False,
            external_agents: tuple[int, ...] = (), external_help: dict[str, str] | None = None,
            view: str | None = None, view_token: str | None = None) -> None:
    """Launch and report. SIGTERM (systemd, `docker stop`) stops every role as Ctrl-C does; a served
    run then ends cleanly (summary.json with `stopped_by`, exit 0: stopping a service is its normal
    end, and Ctrl-C does the same there), a training run is resumable and exits 143 (128 + SIGTERM),
    as Ctrl-C exits 130 (it keeps Ctrl-C's behaviour)."""
    import signal

    from rich.live import Live

    from hammer.deploy.launcher import Stopped, UpError, launch
    from hammer.envs.registry import EnvConfigError

    if resume:
        console.print(f"resuming run dir: {path} (budget {cfg.episodes} episodes)")
    from hammer.deploy.launcher import resolve_agents_per_process

    served = settings.mode == "eval"  # no learner: the policy server publishes the frozen weights
    console.print(_will_run(cfg, settings if resume else resolve_agents_per_process(cfg, settings), path,
                            external_agents), soft_wrap=True)
    from hammer.deploy.live import LiveRun

    try:  # the run's live files for `hammer view` (RUN/live.json), and the view itself with --view
        watch = LiveRun(path, "serve" if served else "up", f"{cfg.env} N={cfg.n_agents} {cfg.wiring.label} seed {cfg.seed}",
                        robots=cfg.n_agents, view=view, token=view_token)
    except ValueError as e:
        fail(str(e))
    if watch.url:
        console.print(f"view: {watch.url}", soft_wrap=True)
    started = time.monotonic()
    rate: dict = {}
    live = None
    last_line = [0.0]
    if dashboard and sys.stderr.isatty():
        live = Live(console=console, refresh_per_second=4, transient=False)
        live.start()

    def tick(board) -> None:
        watch.tick(board)
        if live is not None:
            live.update(dashboard_table(board, cfg, started, settings, rate, path if served else None))
        elif dashboard and time.monotonic() - last_line[0] > 5.0:
            last_line[0] = time.monotonic()
            console.print(status_line(board, cfg, rate))

    signals = (signal.SIGTERM, signal.SIGINT) if served else (signal.SIGTERM,)
    ended = "failed"
    try:
        res = launch(cfg, settings, path, on_tick=tick, resume=resume, external_agents=external_agents,
                     external_help=external_help, stop_signals=signals)
        ended = "completed" if res.stopped_by is None else f"stopped by {res.stopped_by}"
    except Stopped as e:  # before any role started: nothing ran
        if live is not None:
            live.stop()
        console.print(f"stopped by {e.signal_name} before the run started")
        if served:
            return
        raise typer.Exit(128 + signal.Signals[e.signal_name].value) from None
    except EnvConfigError as e:  # a bad or refused env: a config mistake, found before any file is written
        if live is not None:
            live.stop()
        fail(str(e))
    except UpError as e:
        if live is not None:
            live.stop()
        fail(str(e), code=1)
    except KeyboardInterrupt:
        if live is not None:
            live.stop()
        console.print("interrupted: every role was stopped")
        ended = "interrupted"
        raise typer.Exit(130) from None
    finally:
        watch.close(ended)
    if live is not None:
        live.stop()
    s = res.summary
    if res.stopped_by is not None:
        _report_stopped(res, cfg, path, served)
        return
    if s.get("resumed_from") is not None:
        console.print(f"resumed at update {s['resumed_from']}; this session ran {res.wall_time:.0f}s")
    # The verdict goes to stdout (progress and the dashboard stay on stderr): a script reads it there.
    from rich.console import Console

    verdict = Console(soft_wrap=True)
    verdict.print(f"done: {s['episodes']} episodes in {res.wall_time:.0f}s, last-{min(500, s['episodes'])} paper metric "
                  f"{s['final_paper_metric_last500']:.3f}, {s['env_steps_per_s']:,.0f} env-steps/s, "
                  f"step latency p50 {s['step_latency_ms_p50']:.2f} ms p99 {s['step_latency_ms_p99']:.2f} ms -> {path}", markup=False)
    if s.get("degraded"):
        verdict.print(f"[bold red]degraded:[/] {'; '.join(s['degraded_reasons'])} (summary.json)")
    if settings.faults is not None or settings.chaos:
        for link, row in res.links.items():
            console.print(f"{link}: " + ", ".join(f"{k} {v:,}" for k, v in row.items() if v))
        from hammer.faults.links import COUNTERS_NOTE

        console.print(f"({COUNTERS_NOTE})", soft_wrap=True)
    if served:  # a frozen team: nothing to resume or to train further
        return
    from hammer.commands.train import print_next_steps

    print_next_steps(console, cfg, s["final_paper_metric_last500"], path, "hammer up")
