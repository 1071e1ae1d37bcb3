"""`hammer sweep`, `hammer plot`, `hammer report`, `hammer dose`, `hammer diagnose`, `hammer messages`."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from hammer.commands.common import fail


def register(app: typer.Typer) -> None:
    app.command("sweep")(sweep)
    app.command("plot")(plot)
    app.command("report")(report)
    app.command("dose")(dose)
    app.command("diagnose")(diagnose)
    app.command("messages")(messages)




def _load(paths: list[Path]) -> list:
    """Every run under `paths`, or a one-line error."""
    from hammer.experiments.runs import find_runs, load_run

    try:
        loaded = [load_run(p) for p in find_runs(paths)]
    except FileNotFoundError as e:
        fail(str(e))
    if not loaded:
        fail("no run directories (metrics.csv) or archived runs (metrics.npz) found under the given paths")
    # a run that never finished an episode (a serve whose roles never came up, a run killed at once) is no
    # result: noted and left out, so one of them does not block the folder
    empty = [r for r in loaded if len(r.paper_metric) == 0]
    if len(empty) == len(loaded):
        fail(f"no episodes yet in {', '.join(str(r.path) for r in empty[:3])}{' ...' if len(empty) > 3 else ''}")
    if empty:
        shown = ", ".join(str(r.path) for r in empty[:3]) + (f" and {len(empty) - 3} more" if len(empty) > 3 else "")
        typer.echo(f"note: skipped {len(empty)} run{'s' if len(empty) > 1 else ''} with no episodes yet: {shown}",
                   err=True)
    return [r for r in loaded if len(r.paper_metric)]


def sweep(
    out: Annotated[Path, typer.Option(help="Sweep directory; one run directory per grid point inside it.")],
    presets: Annotated[str, typer.Option(help="Comma-separated presets, e.g. cn3,cn5.")] = "cn3",
    variants: Annotated[str, typer.Option(
        help="Comma-separated: hammer, hammer-rl, hammer-backprop, il, random, centralized.")] = "hammer,il",
    seeds: Annotated[str, typer.Option(help="Seeds: a range 0-4 or a list 0,1,2.")] = "0-4",
    grid: Annotated[list[str] | None, typer.Option(
        help="Extra grid axis KEY=V1,V2,... (repeatable), e.g. --grid msg_dim=1,2,4,8.")] = None,
    jobs: Annotated[int | None, typer.Option(help="Runs at once (default: number of cores).")] = None,
    seed_batch: Annotated[int | None, typer.Option(
        help="Most seeds trained in one process (fresh cn points that differ only in seed; default: as many "
             "as free memory allows, up to 16). 1: every point alone, so each run is bit for bit the "
             "`hammer train` of its seed (a batch is statistically equivalent, not bit-identical).", min=1)] = None,
    episodes: Annotated[int | None, typer.Option(
        help="Override the preset's episode budget (the run names then say so, e.g. mw3-il-ep2000-s0).")] = None,
    archive: Annotated[Path | None, typer.Option(
        help="Also keep a compact copy of each finished run here (commit it: runs archived there are "
             "skipped, so the sweep continues from a fresh clone). e.g. docs/results/runs/cn5")] = None,
    snapshot: Annotated[bool, typer.Option(
        help="Run nothing: copy each unfinished run of OUT that has a checkpoint to ARCHIVE/_partial/ "
             "(commit it before the session ends; the next sweep restores and resumes it). Needs --archive; "
             "safe while the sweep runs.")] = False,
    status: Annotated[bool, typer.Option(
        help="Run nothing: print where every point of the grid stands (archived, done, running, "
             "resumable, snapshot, not started) with its episodes and final metric. Safe while the sweep runs.")] = False,
    extend_from: Annotated[Path | None, typer.Option(
        help="A sweep directory holding these points at a shorter budget (e.g. runs/paper/rware5m-2 for a grid "
             "with --episodes 20000): a point with no run yet (here, in --archive or its _partial/) continues "
             "that run from its last checkpoint, as `hammer train --resume RUN --episodes N` would; DIR is not "
             "touched. Refused in one line if that run differs in anything but episodes, has no checkpoint or "
             "is not shorter. With --snapshot: make those continuations and snapshot them, running nothing.")] = None,
    snapshot_every: Annotated[float, typer.Option(
        help="With --archive: also snapshot the runs in progress every this many minutes while the sweep "
             "runs, so a session cut off without warning still leaves them in ARCHIVE/_partial/. 0: never.",
        min=0.0)] = 30.0,
    backend: Annotated[str, typer.Option(
        help="Where the runs run: local (child processes here) or ray (Ray tasks; a private local "
             "instance, or the cluster at --ray-address; OUT must be on storage every node mounts).")] = "local",
    ray_address: Annotated[str | None, typer.Option(
        help="With --backend ray: the cluster to join, e.g. <head-host>:6379 or auto (default: start Ray "
             "on this machine, on 127.0.0.1 only).")] = None,
    ray_cpus: Annotated[float, typer.Option(
        help="With --backend ray: CPUs Ray reserves for each run (a seed batch is one run).", min=0.01)] = 1.0,
) -> None:
    """Run a grid of independent training runs, resumably.

    Re-running the same command skips finished runs, resumes interrupted ones from their last
    checkpoint and starts the rest. Each run is its own run directory under OUT.
    """
    from hammer.console import table_console
    from hammer.experiments.sweep import (
        ExtendError,
        duplicate_points,
        expand,
        extend_points,
        parse_grid_overrides,
        parse_seeds,
        run_sweep,
        snapshot_sweep,
    )

    console = table_console()
    try:
        points = expand(presets.split(","), variants.split(","), parse_seeds(seeds),
                        parse_grid_overrides(grid or []), episodes=episodes)
    except ValueError as e:
        fail(str(e))

    def event(kind: str, name: str) -> None:
        style = {"done": "green", "fail": "red", "skip": "dim", "broken": "yellow", "same": "dim"}.get(kind, "cyan")
        console.print(f"[{style}]{kind:>7}[/] {name}", highlight=False, soft_wrap=True)

    if status:
        _print_status(console, points, out, archive)
        return
    if snapshot:
        if archive is None:
            fail("--snapshot writes into the archive; fix: pass --archive DIR too")
        if extend_from is not None:
            try:
                extend_points(points, out, extend_from, archive, on_event=event)
            except ExtendError as e:
                fail(str(e))
        if not out.is_dir():  # not an error: `make snapshot` covers grids this machine never ran
            console.print(f"snapshot: {out} does not exist here, nothing to snapshot")
            return
        taken = snapshot_sweep(points, out, archive, on_event=event)
        console.print(f"snapshot: {len(taken)} runs in progress -> {archive / '_partial'}")
        return
    dups = duplicate_points(points)
    if dups:
        fields = sorted({f for _, f in dups})
        console.print(f"note: {len(dups)} runs repeat another run of this grid: their variant ignores "
                      f"{', '.join(fields)} (e.g. {dups[0][0].name}); drop those values for that variant "
                      "to save the compute", highlight=False, soft_wrap=True)
    launcher = _launcher(backend, ray_address, ray_cpus)
    console.print(f"sweep: {len(points)} runs into {out}" + (f" ({launcher.describe()})" if backend == "ray" else ""))
    try:
        res = run_sweep(points, out, jobs=jobs, on_event=event, archive=archive, launcher=launcher,
                        snapshot_every_s=snapshot_every * 60.0 if snapshot_every > 0 else None, seed_batch=seed_batch,
                        extend_from=extend_from)
    except ExtendError as e:
        fail(str(e))
    finally:
        launcher.close()
    console.print(f"finished {len(res.done)} ({len(res.restored)} restored from snapshots"
                  + (f", {len(res.extended)} extended from {extend_from}" if extend_from is not None else "") + "), "
                  f"skipped (already done) {len(res.skipped)}, failed {len(res.failed)}")
    if res.failed:
        fail("failed runs: " + ", ".join(f"{n} (exit {c}; see {out / n / 'train.log'})" for n, c in res.failed))


def _launcher(backend: str, ray_address: str | None, ray_cpus: float):
    """The sweep's backend (`experiments.launch`), or a one-line error."""
    if backend == "local":
        if ray_address is not None:
            fail("--ray-address joins a Ray cluster; fix: add --backend ray")
        from hammer.experiments.launch import LocalLauncher

        return LocalLauncher()
    if backend != "ray":
        fail(f"--backend {backend!r}: expected local or ray")
    from hammer.experiments.ray_backend import RayLauncher, RayUnavailable

    try:
        return RayLauncher(ray_address, ray_cpus)
    except RayUnavailable as e:
        fail(str(e))


def _print_status(console, points, out: Path, archive: Path | None) -> None:
    from collections import Counter

    from rich.table import Table

    from hammer.experiments.sweep import sweep_status

    rows = sweep_status(points, out, archive)
    table = Table(title=f"{out}" + (f" (archive {archive})" if archive else ""), title_justify="left")
    for col, kw in (("run", {"no_wrap": True}), ("state", {"no_wrap": True}),
                    ("episodes", {"justify": "right", "no_wrap": True}),
                    ("final", {"justify": "right", "no_wrap": True}), ("note", {})):
        table.add_column(col, **kw)
    style = {"archived": "green", "done": "green", "running": "cyan", "resumable": "yellow",
             "snapshot": "yellow", "started": "yellow"}
    for r in rows:
        eps = f"{r.episodes:,} / {r.budget:,}" if r.episodes is not None else f"- / {r.budget:,}"
        final = f"{r.final:.2f}" if r.final is not None else ""
        table.add_row(r.name, f"[{style.get(r.state, 'dim')}]{r.state}[/]", eps, final, r.note)
    console.print(table)
    console.print("final = mean paper metric of the last 500 episodes (finished runs only)", style="dim")
    counts = Counter(r.state for r in rows)
    console.print(", ".join(f"{n} {k}" for k, n in counts.items()) + f" of {len(rows)}")


def plot(
    runs: Annotated[list[Path], typer.Argument(help="Run directories or folders holding them.")],
    out: Annotated[Path, typer.Option(help="Output path without extension; writes .png and .svg.")] = Path("curves"),
    window: Annotated[int, typer.Option(help="Rolling-mean window in episodes.")] = 500,
    band: Annotated[str, typer.Option(
        help="se: mean over seeds with a standard-error band; iqm: interquartile mean over seeds with a "
             "95 % stratified-bootstrap CI (robust to one outlying seed).")] = "se",
) -> None:
    """Learning curves: paper metric vs episodes, one line per variant, a band over seeds."""
    from hammer.experiments.plot import BANDS, plot_runs

    if band not in BANDS:
        fail(f"--band must be one of {', '.join(BANDS)}, got {band!r}")
    for p in plot_runs(_load(runs), out, window=window, band=band):
        typer.echo(f"wrote {p}")


def report(
    runs: Annotated[list[Path], typer.Argument(help="Run directories or folders holding them.")],
    last: Annotated[int, typer.Option(help="Final performance = mean of each run's last N episodes.")] = 500,
    out: Annotated[Path | None, typer.Option(help="Also write the markdown table here.")] = None,
    export: Annotated[Path | None, typer.Option(
        help="Also write a compact JSON of every run (config, final figures, downsampled curve).")] = None,
    best_window: Annotated[int | None, typer.Option(
        help="Rank each run by its best rolling mean over this many episodes instead of its final mean: "
             "how high it got, not where it ended (runs that learn and then fall back differ).", min=1)] = None,
    auc: Annotated[int | None, typer.Option(
        help="Rank each run by its area under the learning curve: the mean paper metric over its first N "
             "episodes (\"learns faster\"), instead of its final mean.", min=1)] = None,
    comparisons: Annotated[str | None, typer.Option(
        help="The study's declared comparisons as A:B pairs, e.g. 'hammer-rl:il,random:il' (hammer-rl "
             "names hammer-rl-m4 at any message length); Holm's correction runs over exactly these. "
             "Default: every variant against il.")] = None,
    plan: Annotated[Path | None, typer.Option(
        help="Read the comparisons from a pre-registered plan's `comparisons:` line "
             "(docs/results/plan-*.md) instead of --comparisons.", exists=True, dir_okay=False)] = None,
    digits: Annotated[int, typer.Option(help="Decimals of the metric in the tables (the warehouse's deliveries "
                                        "per robot need 3).", min=0, max=8)] = 2,
) -> None:
    """Table of final performance: mean ± standard error, IQM with a bootstrap CI, team return,
    Welch's t-test vs IL; then the declared comparisons with probability of improvement and
    Holm-corrected p-values (experiments/stats.py).

    One row per setting and variant. A setting is the env and N plus every config field the runs
    changed from their paper preset (e.g. `cn N=3 (lr_local=0.0001)`): runs are pooled as seeds
    only when nothing but the seed differs, and IL is compared within the same setting.
    """
    from hammer.experiments.report import (
        build_comparisons,
        build_rows,
        comparisons_from_plan,
        default_comparisons,
        parse_comparisons,
        to_markdown,
    )

    if plan is not None and comparisons is not None:
        fail("--plan and --comparisons both declare the comparisons: give one")
    loaded = _load(runs)
    try:
        rows = build_rows(loaded, last, best_window, auc)
        if plan is not None:
            pairs = comparisons_from_plan(plan)
        elif comparisons is not None:
            pairs = parse_comparisons(comparisons)
        else:
            pairs = default_comparisons(rows)
        comps = build_comparisons(rows, pairs) if pairs else []
        md = to_markdown(rows, last, best_window, comps, auc, digits)
    except ValueError as e:
        fail(str(e))
    typer.echo(md)
    if out:
        out.write_text(md)
    if export:
        from hammer.experiments.export import export_runs

        export_runs(loaded, export)


def dose(
    runs: Annotated[list[Path], typer.Argument(help="Run directories or folders of the dose-response grid "
                                               "(cn runs with and without env_kwargs.obs_radius).")],
    variants: Annotated[str, typer.Option(help="Variants compared with il at each level, comma-separated.")] = (
        "hammer-rl,hammer-backprop,random"),
    auc: Annotated[int | None, typer.Option(
        help="Use the area under the curve over the first N episodes instead of the final value.", min=1)] = None,
    last: Annotated[int, typer.Option(help="Final value = mean of each run's last N episodes.")] = 500,
    out: Annotated[Path | None, typer.Option(help="Write <out>.md (table) and <out>.png/.svg (Δ against h).")] = None,
    learned_h: Annotated[Path | None, typer.Option(
        help="Also write the exploratory table of the fraction hidden while each run's trained team plays "
             "(runs with final/ weights; ~1 s a team).")] = None,
) -> None:
    """Dose-response of hidden information (docs/results/plan-dose-response.md): Δ = IQM(variant) −
    IQM(IL) per obs_radius level with bootstrap CIs, and the slope of Δ on the fraction hidden."""
    from hammer.experiments.dose import (
        cells,
        dose_levels,
        dose_slope,
        learned_hidden_table,
        plot_dose,
        to_markdown,
    )

    loaded = _load(runs)
    measure = "final" if auc is None else "auc"
    try:
        values = cells(loaded, measure, last=last, auc=auc or 0)
    except ValueError as e:
        fail(str(e))
    names = [v for v in variants.split(",") if v]
    levels = [lv for v in names for lv in dose_levels(values, v)]
    if not levels:
        fail(f"no level has runs of both il and one of {', '.join(names)}")
    slopes = [s for v in names if (s := dose_slope(values, v)) is not None]
    md = to_markdown(levels, slopes, measure if auc is None else f"AUC {auc}")
    typer.echo(md)
    if out:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.with_suffix(".md").write_text(md)
        for p in plot_dose(levels, out):
            typer.echo(f"wrote {p}")
    if learned_h:
        learned_h.parent.mkdir(parents=True, exist_ok=True)
        learned_h.write_text(table := learned_hidden_table(loaded))
        typer.echo(table)


def diagnose(
    runs: Annotated[list[Path], typer.Argument(help="Run directories, archived runs or folders holding them.")],
    out: Annotated[Path | None, typer.Option(
        help="Also draw the figure: output path without extension; writes .png and .svg.")] = None,
    table: Annotated[Path | None, typer.Option(help="Also write the markdown table here.")] = None,
    window: Annotated[int, typer.Option(help="Rolling-mean window in episodes for the best point.")] = 500,
    last: Annotated[int, typer.Option(help="Final performance = mean of each run's last N episodes.")] = 500,
) -> None:
    """Why did a run fall back after it had learned? Learner statistics around each run's peak.

    Per run: its best rolling mean and final score next to its local learner's policy entropy (at
    the best episode and at the end) and the median approximate KL and clip fraction of its
    updates before and after the best episode.

    Reads the learner statistics from an archived run's train_stats.npz or a run directory's
    TensorBoard events (tb/); runs with neither show a dash.
    """
    from hammer.experiments.diagnose import diagnose as diagnose_run
    from hammer.experiments.diagnose import plot_diagnostics, to_markdown
    from hammer.experiments.train_stats import load_train_stats

    loaded = _load(runs)
    try:
        stats = {r.path: load_train_stats(r.path) for r in loaded}  # read once: the table and the figure
        diags = [diagnose_run(r, window, last, stats[r.path]) for r in loaded]
    except ValueError as e:
        fail(str(e))
    md = to_markdown(diags, window, last)
    typer.echo(md)
    if table:
        table.write_text(md)
    if out:
        for p in plot_diagnostics(loaded, out, window=window, stats=stats):
            typer.echo(f"wrote {p}")


def messages(
    runs: Annotated[list[Path], typer.Argument(help="Archived runs with final/ weights, or folders holding them "
                                               "(hammer and random teams are analysed, the others skipped).")],
    out: Annotated[Path, typer.Option(help="Output path without extension: writes <out>.md (tables) and <out>.json "
                                      "(every team's result; re-read so unchanged teams are not recomputed; while it "
                                      "runs, <out>.partial.json keeps each finished team, so a run cut short resumes)."
                                      )],
    figure: Annotated[Path | None, typer.Option(
        help="messages-episode.png: one episode of each setting's hammer-rl team of training seed 0.")] = None,
    episodes: Annotated[int, typer.Option(help="Evaluation episodes per evaluation seed.", min=10)] = 500,
    eval_seeds: Annotated[str, typer.Option(help="Evaluation seeds: a range 0-1 or a list 0,1.")] = "0-1",
    fresh: Annotated[bool, typer.Option(help="Recompute every team, ignoring <out>.json.")] = False,
    teams: Annotated[str | None, typer.Option(
        help="Only teams whose label starts with one of these, comma-separated, e.g. hammer-rl,random "
             "(the dose-response grid's plan analyses those two).")] = None,
    jobs: Annotated[int, typer.Option(help="Teams analysed at once, one process each (the results do not "
                                      "depend on it).", min=1)] = 1,
) -> None:
    """What the messages say (docs/results/plan-messages.md): each trained team acts with its frozen weights
    (the runtime's numpy acting code, in this process), ridge probes from each message to what its receiver
    cannot see (episode-split CV, gain over the receiver's own observation), hammer-rl vs random with Welch,
    IQM difference, P(A > B) and Holm, and the team's paper-metric drop when one agent's message is cut."""
    import json

    from hammer.experiments.messages import MessagesError
    from hammer.experiments.messages_report import (
        analyse,
        figure_paths,
        method_header,
        plot_episode,
        select_teams,
        to_markdown,
    )
    from hammer.experiments.sweep import parse_seeds

    try:
        seeds = parse_seeds(eval_seeds)
        found = select_teams(runs, teams.split(",") if teams else None)
    except (ValueError, FileNotFoundError) as e:
        fail(str(e))
    for what, skipped in (("no messages (il, centralized)", found.no_messages),
                          ("no final/ weights in the archive", found.no_weights)):
        if skipped:
            typer.echo(f"skipped {len(skipped)} runs with {what}: {', '.join(p.name for p in skipped[:4])}"
                       + (" ..." if len(skipped) > 4 else ""))
    if not found.teams:
        fail("no team with messages and final/ weights under the given paths")
    js, part = out.with_suffix(".json"), out.with_suffix(".partial.json")
    previous = [] if fresh else [r for f in (js, part) if f.is_file() for r in json.loads(f.read_text())["results"]]

    def save(done: list[dict]) -> None:  # an analysis cut short resumes from here (not a result: no table)
        part.parent.mkdir(parents=True, exist_ok=True)
        tmp = part.with_suffix(".tmp")
        tmp.write_text(json.dumps({"eval_seeds": seeds, "episodes": episodes, "partial": True, "results": done}))
        tmp.replace(part)

    def progress(k: int, n: int, res: dict, how: str) -> None:
        typer.echo(f"[{k}/{n}] {how} {Path(res['run']).name}: paper metric {res['paper_metric']:.2f}, gains "
                   + ", ".join(f"{t} {v['gain']:+.3f}" for t, v in res["probes"].items()))

    try:
        results = analyse(found.teams, seeds, episodes, previous, progress, jobs=jobs, save=save)
    except MessagesError as e:
        fail(str(e))
    md = to_markdown(results, method_header(len(results), seeds, episodes))
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text(md)
    js.write_text(json.dumps({"eval_seeds": seeds, "episodes": episodes, "results": results}, indent=1))
    part.unlink(missing_ok=True)
    typer.echo(md)
    if figure is not None:
        for path, team in figure_paths(results, figure).items():
            typer.echo(f"wrote {plot_episode(team, path)}")
