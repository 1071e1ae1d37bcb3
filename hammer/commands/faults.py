"""`hammer faults ...`: evaluate trained teams under communication faults."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer

from hammer.commands.common import fail

faults_app = typer.Typer(help="Communication faults as an experiment: evaluate trained teams under drops, "
                              "delays and process chaos.", no_args_is_help=True)


def register(app: typer.Typer) -> None:
    app.add_typer(faults_app, name="faults")




def _floats(text: str, what: str) -> list[float]:
    try:
        return [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        fail(f"--{what} {text!r}: expected comma-separated numbers, e.g. 0,0.1,0.25")
    return []


def _team_arg(item: str) -> tuple[str, Path]:
    label, eq, path = item.partition("=")
    return (label, Path(path)) if eq else (Path(item).name, Path(item))


@faults_app.command("sweep")
def sweep_command(
    runs: Annotated[list[str], typer.Argument(help="Trained teams to evaluate: bundles (`hammer export`) or run "
                                                   "directories (their final/ policy), optionally LABEL=DIR, "
                                                   "e.g. hammer=runs/a hammer+dropout=runs/b.")],
    il: Annotated[Path | None, typer.Option(help="A trained IL run: evaluated without faults as the reference line.")] = None,
    drops: Annotated[str, typer.Option(help="central->local drop rates.")] = "0,0.1,0.25,0.5,1.0",
    delays_ms: Annotated[str, typer.Option(help="central->local delays in ms (0 = none), at drop 0.")] = "25,100",
    seeds: Annotated[int, typer.Option(help="Seeds per point (env resets, sampling and fault streams).")] = 3,
    episodes: Annotated[int, typer.Option(help="Episodes per point and seed.")] = 200,
    msg_deadline_ms: Annotated[float, typer.Option(help="How long a local agent waits for its message.")] = 50.0,
    parallel: Annotated[int, typer.Option(help="Evaluation runs at a time.")] = 2,
    out: Annotated[Path, typer.Option(help="Output directory (sweep.csv, sweep.md, sweep.png, points/).")] = Path(
        "runs/faults-sweep"),
) -> None:
    """Evaluate trained teams (real runtime, frozen weights) under a grid of message drop rates and
    delays, several seeds each; writes a CSV, a markdown table and a plot with the IL reference line."""
    from hammer.experiments.fault_sweep import SweepMismatch, grid, run_sweep
    from hammer.serve.bundle import BundleError, is_bundle, load_bundle

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    teams = dict(_team_arg(r) for r in runs)
    for label, path in [*teams.items(), *([("il", il)] if il else [])]:
        if is_bundle(path):
            try:
                load_bundle(path)
            except BundleError as e:
                fail(f"{label}: {e}")
        elif not (path / "final" / "local.safetensors").is_file():
            fail(f"{label}: {path}/final/local.safetensors is missing; fix: pass a bundle or a finished run directory")
    points = grid(teams, il, _floats(drops, "drops"), _floats(delays_ms, "delays-ms"), list(range(seeds)))
    typer.echo(f"{len(points)} evaluation runs ({episodes} episodes each, {parallel} at a time) -> {out}; "
               "Ctrl-C stops, the same command continues")

    def progress(r, i, n) -> None:
        typer.echo(f"[{i}/{n}] {r.team} drop {r.drop:g} delay {r.delay_ms:g} ms seed {r.seed}: metric "
                   f"{r.paper_metric:.2f}, fallbacks {r.msg_fallback_rate:.0%}, late {r.msgs_late}, {r.wall_s:.0f}s")

    try:
        res = run_sweep(points, out, episodes, msg_deadline_ms, parallel, progress, note=typer.echo)
    except SweepMismatch as e:
        fail(str(e))
    wrote = (f"wrote {out / 'sweep.csv'}, {out / 'sweep.md'}, {out / 'sweep.png'}" if res.results
             else "nothing written")
    if res.stopped_by is not None:
        import shlex
        import signal
        import sys

        again = shlex.join(["hammer", *sys.argv[1:]])
        typer.echo(f"stopped by {res.stopped_by}: {len(res.results)} of {len(points)} evaluation runs finished, "
                   f"{wrote}; continue with the same command: {again}", err=True)
        raise typer.Exit(128 + signal.Signals[res.stopped_by].value)
    if res.results:
        typer.echo((out / "sweep.md").read_text())
    typer.echo(wrote)
    for name, reason in res.failed:
        typer.echo(f"failed: {name}: {reason} (log: {out / 'points' / name / 'logs'})", err=True)
    if res.failed:
        fail(f"{len(res.failed)} of {len(points)} evaluation runs failed (above); the same command evaluates them "
             "again and keeps the finished ones", code=1)


@faults_app.command("eval")
def eval_command(
    run: Annotated[Path, typer.Argument(help="Trained team: a bundle (`hammer export`) or a run directory "
                                             "(its final/ policy).")],
    fault: Annotated[list[str] | None, typer.Option(
        "--fault", help="LINK:FIELD=VALUE,... e.g. 'central->local:agent=1,drop=0.2,delay_ms=5,jitter_ms=2'.")] = None,
    fault_seed: Annotated[int, typer.Option(help="Seed of the fault streams.")] = 0,
    chaos: Annotated[list[str] | None, typer.Option(
        "--chaos", help="ACTION:ROLE@step=N|t=S[,for=S], e.g. 'kill:central@step=200,for=3s'.")] = None,
    episodes: Annotated[int, typer.Option(help="Episodes to evaluate.")] = 200,
    seed: Annotated[int, typer.Option(help="Evaluation seed.")] = 0,
    runtime: Annotated[list[str] | None, typer.Option(
        "--runtime", help="RuntimeSettings field=value, e.g. msg_deadline_ms=20, fallback=last_k.")] = None,
    run_dir: Annotated[Path | None, typer.Option(help="Where to write the evaluation run.")] = None,
) -> None:
    """One evaluation of a trained team under the given link faults and chaos; prints per-link counters."""
    import json
    import time

    from hammer.deploy.launcher import UpError, launch
    from hammer.experiments.fault_sweep import eval_config, eval_settings

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    path = run_dir or run.parent / f"{run.name}-eval-{time.strftime('%Y%m%d-%H%M%S')}"
    try:
        cfg = eval_config(run, episodes, seed)
        settings, plan = eval_settings(run, path.name.replace("_", "-")[:64], fault, fault_seed, chaos, runtime)
    except (FileNotFoundError, ValueError) as e:  # FaultSpecError, ChaosSpecError, BundleError: one line
        fail(str(e))
    for lf in plan.links:
        typer.echo(f"fault: {lf.describe()} (seed {plan.seed})")
    try:
        res = launch(cfg, settings, path)
    except UpError as e:
        fail(str(e), code=1)
    s = res.summary
    typer.echo(f"{s['episodes']} episodes, mean paper metric {s['final_paper_metric_last500']:.3f} -> {path}")
    for ev in res.chaos_log:
        typer.echo(f"chaos: {ev}")
    typer.echo(json.dumps(res.links, indent=1))
