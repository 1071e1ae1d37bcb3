"""`hammer up` and the role commands."""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path
from typing import Annotated

import typer


def _fail(msg: str, code: int = 2) -> None:
    typer.secho(f"error: {msg}", fg=typer.colors.RED, err=True)
    raise typer.Exit(code)


def register(app: typer.Typer, bench: typer.Typer) -> None:
    from deploy import roles

    app.command("up")(up_command)
    app.command("env-host")(roles.env_host_command)
    app.command("central")(roles.central_command)
    app.command("local")(roles.local_command)
    app.command("learner")(roles.learner_command)


def _dashboard_table(board, cfg, started: float):
    from rich.table import Table

    env = board.heartbeats.get("env")
    c = env.counters if env else {}
    t = Table(title=f"hammer up: {cfg.env} N={cfg.n_agents} {cfg.variant}"
                    f"{'/' + cfg.central_mode if cfg.variant == 'hammer' else ''} seed {cfg.seed}",
              show_header=True, expand=False)
    t.add_column("what")
    t.add_column("value", justify="right")
    t.add_row("episodes", f"{int(c.get('episodes', 0)):,} / {cfg.episodes:,}")
    t.add_row("paper metric (last 100)", f"{c.get('paper_metric_100', float('nan')):.2f}")
    t.add_row("env-steps/s", f"{board.env_rate():,.0f}")
    t.add_row("step latency p50 / p99 (ms)", f"{c.get('step_p50_ms', 0):.2f} / {c.get('step_p99_ms', 0):.2f}")
    t.add_row("late / duplicate actions", f"{int(c.get('actions_late', 0))} / {int(c.get('actions_duplicate', 0))}")
    t.add_row("default actions / msg fallbacks", f"{int(c.get('default_actions', 0))} / "
                                                 f"{int(c.get('msg_fallback_copies', 0))}")
    versions = ", ".join(f"{r}:{int(h.counters.get('policy_version', -1))}" for r, h in sorted(board.heartbeats.items()))
    t.add_row("policy version per role", versions or "-")
    restarts = ", ".join(f"{r}:{n}" for r, n in sorted(board.restarts.items()) if n)
    t.add_row("roles alive / restarts", f"{len(board.alive)} / {restarts or 0}")
    t.add_row("elapsed", f"{time.monotonic() - started:,.0f} s")
    return t


def up_command(
    config: Annotated[Path | None, typer.Argument(help="Optional YAML file of RunConfig fields.")] = None,
    preset: Annotated[str, typer.Option(help="cn3 | cn5 | mw3 | mw5 (the paper's settings).")] = "cn3",
    variant: Annotated[str | None, typer.Option(help="hammer | il | random | centralized (default hammer).")] = None,
    central_mode: Annotated[str | None, typer.Option(help="rl (paper text) | backprop (authors' code).")] = None,
    seed: Annotated[int | None, typer.Option(help="Run seed.")] = None,
    episodes: Annotated[int | None, typer.Option(help="Episode budget (default: the preset's).")] = None,
    set_: Annotated[list[str] | None, typer.Option("--set", help="RunConfig field=value, repeatable.")] = None,
    runtime: Annotated[list[str] | None, typer.Option(
        "--runtime", help="RuntimeSettings field=value, repeatable, e.g. msg_deadline_ms=20, fallback=last.")] = None,
    faults: Annotated[Path | None, typer.Option(help="JSON/YAML FaultSpec file (seeded drop/delay/duplicate/reorder rules).")] = None,
    out: Annotated[str, typer.Option(help="Root directory for run directories.")] = "runs",
    run_dir: Annotated[Path | None, typer.Option(help="Exact run directory (default: OUT/up-<name>-<time>).")] = None,
    dashboard: Annotated[bool, typer.Option(help="Live terminal dashboard (plain status lines when not a TTY).")] = True,
) -> None:
    """Run a whole experiment as separate processes over Zenoh on this host.

    Starts the learner, the central agent (hammer/random), one client per local agent and the env
    host, each a fresh interpreter; waits until all are alive; trains to the episode budget;
    stops everything. Ctrl-C stops cleanly. Logs of every process are in RUN_DIR/logs/.
    """
    import yaml
    from rich.console import Console
    from rich.live import Live

    from deploy.settings import RuntimeSettings
    from deploy.up import UpError, launch
    from learning.config import ConfigError, merge_config
    from protocol.faults import FaultSpec

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    console = Console(stderr=True)
    try:
        cfg = merge_config(preset, config, set_ or [], {"variant": variant or "hammer", "central_mode": central_mode,
                                                        "seed": seed, "episodes": episodes, "out": out})
    except ConfigError as e:
        _fail(str(e))
    path = run_dir or Path(out) / f"up-{cfg.run_name()}-{time.strftime('%Y%m%d-%H%M%S')}"
    rt: dict = {"run_id": path.name.replace("_", "-")[:64]}
    for item in runtime or []:
        key, eq, val = item.partition("=")
        if not eq:
            _fail(f"--runtime {item!r}: expected FIELD=VALUE, e.g. msg_deadline_ms=20")
        rt[key.strip()] = yaml.safe_load(val)
    if faults is not None:
        try:
            rt["faults"] = FaultSpec.model_validate(yaml.safe_load(faults.read_text()))
        except Exception as e:  # noqa: BLE001 - report any parse/validation problem in one line
            _fail(f"--faults {faults}: {str(e).splitlines()[0]}")
    try:
        settings = RuntimeSettings.model_validate(rt)
    except Exception as e:  # noqa: BLE001
        _fail(f"--runtime: {' '.join(str(e).split())}")
    console.print(f"run dir: {path}")
    if settings.faults is not None and settings.faults.enabled:
        for r in settings.faults.rules:
            console.print(f"fault rule: {r.model_dump()}")
    started = time.monotonic()
    live = None
    last_line = [0.0]
    if dashboard and sys.stderr.isatty():
        live = Live(console=console, refresh_per_second=4, transient=False)
        live.start()

    def tick(board) -> None:
        if live is not None:
            live.update(_dashboard_table(board, cfg, started))
        elif dashboard and time.monotonic() - last_line[0] > 5.0:
            last_line[0] = time.monotonic()
            env = board.heartbeats.get("env")
            c = env.counters if env else {}
            console.print(f"episodes {int(c.get('episodes', 0))}/{cfg.episodes}  "
                          f"env-steps/s {board.env_rate():,.0f}  metric(100) {c.get('paper_metric_100', 0):.2f}  "
                          f"p50/p99 {c.get('step_p50_ms', 0):.2f}/{c.get('step_p99_ms', 0):.2f} ms  "
                          f"defaults {int(c.get('default_actions', 0))}  fallbacks {int(c.get('msg_fallback_copies', 0))}")

    try:
        res = launch(cfg, settings, path, on_tick=tick)
    except UpError as e:
        if live is not None:
            live.stop()
        _fail(str(e), code=1)
    except KeyboardInterrupt:
        if live is not None:
            live.stop()
        console.print("interrupted: every role was stopped")
        raise typer.Exit(130) from None
    if live is not None:
        live.stop()
    s = res.summary
    console.print(f"done: {s['episodes']} episodes in {res.wall_time:.0f}s, last-500 paper metric "
                  f"{s['final_paper_metric_last500']:.3f}, {s['env_steps_per_s']:,.0f} env-steps/s, "
                  f"step latency p50 {s['step_latency_ms_p50']:.2f} ms p99 {s['step_latency_ms_p99']:.2f} ms -> {path}")
