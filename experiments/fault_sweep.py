"""The communication-faults experiment: a trained team under a grid of drop rates and delays.

Every point is a real `hammer up` run in evaluation mode (frozen exported policy served by
`serve.policy_server`, env host never waiting for updates, every hop over Zenoh) with a seeded
fault on the central->local link: drop rate p, or a delay d (beyond the message deadline the
message always comes too late, which must behave like a drop, counted as late). Several seeds per
point: the seed sets the env resets, the agents' sampling streams and the fault stream. A team
trained without messages (IL) evaluated without faults is the reference line: a team that does no
better than it with messages cut has learned nothing robust from them.

Outputs (in `out`): sweep.csv (one row per point and seed), sweep.md (mean ± std over seeds per
condition and team, plus the fallback rate), sweep.png (paper metric vs drop rate and vs delay).
"""

from __future__ import annotations

import csv
import json
import logging
import math
import shutil
import signal
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from hammer.protocol.structs import dump, replace

log = logging.getLogger("hammer.experiments.fault_sweep")


@dataclass(frozen=True)
class Point:
    team: str  # a label, e.g. "hammer" or "hammer+dropout"
    run: str  # the trained team: a bundle, or a run directory (its final/ is evaluated)
    drop: float
    delay_ms: float
    seed: int

    @property
    def name(self) -> str:
        return f"{self.team}-drop{self.drop:g}-delay{self.delay_ms:g}-seed{self.seed}".replace("+", "_")


@dataclass
class PointResult:
    team: str
    variant: str
    train_msg_dropout: float
    drop: float
    delay_ms: float
    seed: int
    episodes: int
    paper_metric: float
    msgs_sent: int
    msgs_dropped: int
    msgs_late: int
    msg_fallback_rate: float  # agent x copy entries acted on a fallback message / all entries
    default_actions: int
    wall_s: float


def team_source(run: Path) -> tuple[dict, Path]:
    """(config fields, policy directory) of a trained team: a bundle (`hammer export`, checked whole)
    or a run directory (its final/ policy)."""
    from hammer.serve.bundle import is_bundle, load_bundle

    run = Path(run)
    if is_bundle(run):
        b = load_bundle(run)
        return b.config_data, b.policy_dir
    path = run / "config.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: pass a bundle (`hammer export`) or a run directory made by "
                                "`hammer train` or `hammer up`")
    return json.loads(path.read_text()), run / "final"


def eval_config(run: Path, episodes: int, seed: int):
    """The trained team's config for evaluation: its task and networks, a new seed and budget,
    no message dropout (the evaluation's faults come from the fault layer)."""
    from hammer.learning.config import build_config

    data, _ = team_source(run)
    data.update(episodes=episodes, seed=seed, msg_dropout=0.0)
    return build_config(data)


def eval_settings(run: Path, run_id: str, fault: list[str] | None = None, fault_seed: int = 0,
                  chaos: list[str] | None = None, runtime: list[str] | None = None):
    """(RuntimeSettings, FaultPlan) of an evaluation of a trained team (`hammer faults eval`, each sweep
    point): eval mode, link faults, chaos, --runtime items. A bundle is served as `hammer serve` serves
    it (serve.served_settings.serve_settings: its fallback applies); a run directory's final/ policy with the
    default fallback. ValueError (FaultSpecError, ChaosSpecError, BundleError) with one line."""
    from hammer.faults.chaos import parse_chaos
    from hammer.faults.spec import build_plan
    from hammer.runtime.settings import build_settings
    from hammer.serve.bundle import is_bundle, load_bundle

    run = Path(run)
    if is_bundle(run):
        from hammer.serve.served_settings import serve_settings

        return serve_settings(load_bundle(run), run_id, fault, fault_seed, chaos, runtime)
    plan = build_plan(fault, fault_seed)
    for c in chaos or []:
        parse_chaos(c)
    rt = {"run_id": run_id, "mode": "eval", "policy_dir": str(team_source(run)[1]),
          "faults": plan.to_spec(), "chaos": chaos or [], "fault_links": [dump(lf) for lf in plan.links]}
    return build_settings(rt, runtime), plan


def point_settings(p: Point, msg_deadline_ms: float, fault_seed_base: int = 1000):
    """RuntimeSettings of one sweep point: eval mode (`eval_settings`), the point's fault on central->local."""
    from hammer.faults.spec import FaultPlan, LinkFault

    links = [] if p.drop == 0 and p.delay_ms == 0 else [LinkFault(link="central->local", drop=p.drop, delay_ms=p.delay_ms)]
    plan = FaultPlan(seed=fault_seed_base + p.seed, links=links)
    faults = {"faults": plan.to_spec(), "fault_links": [dump(lf) for lf in links]}
    base, _ = eval_settings(Path(p.run), p.name.replace(".", "_")[:64], runtime=[f"msg_deadline_ms={msg_deadline_ms}"])
    return replace(base, **faults)


POINT_FILE = "point.json"  # a finished point's result, written last: its presence marks the point done


class SweepMismatch(ValueError):
    """A finished point in `out` was evaluated with other settings than this sweep asks."""


def run_point(p: Point, out: Path, episodes: int, msg_deadline_ms: float, fault_seed_base: int = 1000,
              stop=None) -> PointResult:
    """Evaluate one point into out/points/<name> (launch's `stop` passed on) and record its result
    there (POINT_FILE)."""
    from hammer.deploy.launcher import launch

    run = Path(p.run)
    trained, _ = team_source(run)
    cfg = eval_config(run, episodes, p.seed)
    settings = point_settings(p, msg_deadline_ms, fault_seed_base)
    t0 = time.monotonic()
    point_dir = out / "points" / p.name
    res = launch(cfg, settings, point_dir, stop=stop)
    if res.stopped_by is not None:
        from hammer.runtime.process import Stopped

        raise Stopped(res.stopped_by)
    with open(point_dir / "metrics.csv", newline="") as f:
        metrics = [float(r["paper_metric"]) for r in csv.DictReader(f)]
    c2l = res.links.get("central->local", {})
    n_entries = max(int(res.summary.get("step", 0)) * cfg.n_agents * cfg.num_envs, 1)
    r = PointResult(team=p.team, variant=cfg.variant, train_msg_dropout=float(trained.get("msg_dropout", 0.0)), drop=p.drop, delay_ms=p.delay_ms, seed=p.seed,
        episodes=len(metrics), paper_metric=sum(metrics) / len(metrics), msgs_sent=c2l.get("sent", 0),
        msgs_dropped=c2l.get("dropped", 0), msgs_late=c2l.get("late", 0),
        msg_fallback_rate=c2l.get("fallbacks", 0) / n_entries, default_actions=res.links["local->env"]["defaults"],
        wall_s=round(time.monotonic() - t0, 1))
    asked = {"run": p.run, "episodes": episodes, "msg_deadline_ms": msg_deadline_ms, "fault_seed_base": fault_seed_base}
    (point_dir / POINT_FILE).write_text(json.dumps({"asked": asked, "result": asdict(r)}, indent=1))
    return r


def finished_point(p: Point, out: Path, episodes: int, msg_deadline_ms: float,
                   fault_seed_base: int = 1000) -> PointResult | None:
    """The result of a point finished in an earlier run of this sweep (None: not finished there).
    A point finished with other settings is an error (SweepMismatch), never silently mixed in."""
    path = out / "points" / p.name / POINT_FILE
    try:
        data = json.loads(path.read_text())
        r = PointResult(**data["result"])
        done_with = data["asked"]
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError):
        return None  # unreadable: evaluated again
    asked = {"run": p.run, "episodes": episodes, "msg_deadline_ms": msg_deadline_ms, "fault_seed_base": fault_seed_base}
    diff = [f"{k}={done_with.get(k)!r} (now {v!r})" for k, v in asked.items() if done_with.get(k) != v]
    if diff:
        raise SweepMismatch(f"{path.parent} was evaluated with {', '.join(diff)}; fix: the same arguments as "
                            f"then, or another --out")
    return r


@dataclass
class SweepOutcome:
    results: list[PointResult]  # finished points, this run's and earlier runs' (in grid order)
    skipped: int = 0  # finished in an earlier run of the sweep
    failed: list[tuple[str, str]] = field(default_factory=list)  # (point, one-line reason)
    stopped_by: str | None = None  # the signal that stopped the sweep (the rest did not run)


def grid(teams: dict[str, Path], il: Path | None, drops: list[float], delays_ms: list[float],
         seeds: list[int]) -> list[Point]:
    pts = []
    for team, run in teams.items():
        for s in seeds:
            pts += [Point(team, str(run), d, 0.0, s) for d in drops]
            pts += [Point(team, str(run), 0.0, dl, s) for dl in delays_ms if dl > 0]
    if il is not None:
        pts += [Point("il", str(il), 0.0, 0.0, s) for s in seeds]
    return pts


def run_sweep(points: list[Point], out: Path, episodes: int, msg_deadline_ms: float, parallel: int = 2,
              progress: Callable[[PointResult, int, int], None] | None = None,
              note: Callable[[str], None] | None = None,
              stop_signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> SweepOutcome:
    """Run every point not finished yet (`parallel` launches at a time: most of a faulty point is
    waiting on deadlines, not computing) and write sweep.csv / sweep.md / sweep.png of every finished
    point into `out`. Resumable: a point finished by an earlier run into `out` is taken from its
    POINT_FILE; an unfinished one (interrupted, failed) is evaluated again from the start (an
    evaluation has nothing to resume).

    Each of `stop_signals` (main thread only; Ctrl-C, `kill`) stops the sweep at once: no further
    point starts, the running ones are stopped (launch's `stop`), and what finished is written;
    SweepOutcome.stopped_by names the signal. A point that fails is reported, not fatal to the rest.
    `note(text)`: what was found finished, before anything runs."""
    out.mkdir(parents=True, exist_ok=True)
    outcome = SweepOutcome(results=[])
    done: dict[Point, PointResult] = {}
    todo = []
    for p in points:
        r = finished_point(p, out, episodes, msg_deadline_ms)
        if r is None:
            todo.append(p)
        else:
            done[p] = r
    outcome.skipped = len(done)
    if done and note is not None:
        note(f"{len(done)} of {len(points)} evaluation runs already finished in {out / 'points'}; "
             f"evaluating the other {len(todo)}")
    from hammer.runtime.process import take_signals

    stopped: list[str] = []
    _, restore = take_signals(stop_signals, stopped.append)
    try:
        with ThreadPoolExecutor(max_workers=max(1, parallel)) as ex:
            futures = {}
            for p in todo:
                shutil.rmtree(out / "points" / p.name, ignore_errors=True)  # an unfinished evaluation's leftovers
                futures[ex.submit(run_point, p, out, episodes, msg_deadline_ms,
                                  stop=lambda: stopped[0] if stopped else None)] = p
            pending = set(futures)
            while pending:
                finished, pending = wait(pending, timeout=0.2, return_when=FIRST_COMPLETED)
                if stopped:
                    for f in pending:
                        f.cancel()  # not started yet: never starts; the running ones stop themselves
                for f in finished:
                    p = futures[f]
                    if f.cancelled():
                        continue
                    try:
                        r = f.result()
                    except Exception as e:  # noqa: BLE001 - one point's failure is reported, the others go on
                        if not stopped:
                            outcome.failed.append((p.name, " ".join(str(e).split()) or type(e).__name__))
                            log.warning("%s failed: %s", p.name, outcome.failed[-1][1])
                        continue
                    except KeyboardInterrupt:  # launch's Stopped: the sweep is stopping
                        continue
                    done[p] = r
                    if progress is not None:
                        progress(r, len(done), len(points))
    finally:
        restore()
    outcome.stopped_by = stopped[0] if stopped else None
    outcome.results = [done[p] for p in points if p in done]
    if outcome.results:
        write_outputs(outcome.results, out, msg_deadline_ms, episodes)
    return outcome


def _mean_std(xs: list[float]) -> tuple[float, float]:
    m = sum(xs) / len(xs)
    return m, math.sqrt(sum((x - m) ** 2 for x in xs) / max(len(xs) - 1, 1))


def aggregate(results: list[PointResult]) -> dict[tuple[str, float, float], dict]:
    groups: dict[tuple[str, float, float], list[PointResult]] = {}
    for r in results:
        groups.setdefault((r.team, r.drop, r.delay_ms), []).append(r)
    out = {}
    for key, rs in groups.items():
        m, s = _mean_std([r.paper_metric for r in rs])
        out[key] = {"mean": m, "std": s, "n": len(rs), "fallback": sum(r.msg_fallback_rate for r in rs) / len(rs),
                    "late": sum(r.msgs_late for r in rs), "dropped": sum(r.msgs_dropped for r in rs)}
    return out


def read_results(path: Path) -> list[PointResult]:
    """The rows of a sweep.csv written by `write_outputs`, typed again (for analyses of finished sweeps)."""
    types = {"str": str, "int": int, "float": float}
    with open(path, newline="") as f:
        return [PointResult(**{fl.name: types[fl.type](row[fl.name]) for fl in fields(PointResult)})
                for row in csv.DictReader(f)]


def write_outputs(results: list[PointResult], out: Path, msg_deadline_ms: float, episodes: int) -> None:
    with open(out / "sweep.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(asdict(results[0])))
        w.writeheader()
        for r in results:
            w.writerow(asdict(r))
    agg = aggregate(results)
    teams = [t for t in dict.fromkeys(r.team for r in results) if t != "il"]
    conds = sorted({(r.drop, r.delay_ms) for r in results if r.team != "il"}, key=lambda c: (c[1] > 0, c[1], c[0]))
    seeds = sorted({r.seed for r in results})
    il = agg.get(("il", 0.0, 0.0))
    def pm(a: dict) -> str:  # one seed has no spread to show
        return f"{a['mean']:.2f} ± {a['std']:.2f}" if a["n"] > 1 else f"{a['mean']:.2f}"

    header = (f"Paper metric (mean reward per local agent per episode, higher is better), "
              f"{'mean ± std over ' if len(seeds) > 1 else ''}{len(seeds)} seed{'s' if len(seeds) > 1 else ''} "
              f"× {episodes} episodes; central→local faults; message deadline "
              f"{msg_deadline_ms:g} ms; fallback: the bundle's (zeros for a run directory). In brackets: share of agent-steps acting on a fallback message.")
    lines = [header, ""]
    if il is not None:
        lines += [f"IL reference (no messages, no faults): **{pm(il)}**", ""]
    lines += ["| condition | " + " | ".join(teams) + " |", "|---|" + "---|" * len(teams)]
    for drop, delay in conds:
        label = f"drop {drop:g}" if delay == 0 else f"delay {delay:g} ms ({'beyond' if delay > msg_deadline_ms else 'within'} deadline)"
        cells = []
        for t in teams:
            a = agg.get((t, drop, delay))
            cells.append("-" if a is None else f"{pm(a)} ({a['fallback']:.0%})")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    (out / "sweep.md").write_text("\n".join(lines) + "\n")
    _plot(agg, teams, conds, il, msg_deadline_ms, out / "sweep.png")


def _plot(agg, teams, conds, il, msg_deadline_ms, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    drops = sorted({d for d, dl in conds if dl == 0})
    delays = sorted({dl for d, dl in conds if d == 0})
    for t in teams:
        pts = [(d, agg[(t, d, 0.0)]) for d in drops if (t, d, 0.0) in agg]
        ax1.errorbar([d for d, _ in pts], [a["mean"] for _, a in pts], yerr=[a["std"] for _, a in pts],
                     marker="o", capsize=3, label=t)
        pts = [(dl, agg[(t, 0.0, dl)]) for dl in delays if (t, 0.0, dl) in agg]
        ax2.errorbar([dl for dl, _ in pts], [a["mean"] for _, a in pts], yerr=[a["std"] for _, a in pts],
                     marker="o", capsize=3, label=t)
    for ax in (ax1, ax2):
        if il is not None:
            ax.axhline(il["mean"], color="gray", linestyle="--", label="IL (no messages)")
            ax.axhspan(il["mean"] - il["std"], il["mean"] + il["std"], color="gray", alpha=0.15)
        ax.grid(alpha=0.3)
    ax2.axvline(msg_deadline_ms, color="red", linestyle=":", label="message deadline")
    ax1.set_xlabel("central→local drop rate")
    ax2.set_xlabel("central→local delay (ms)")
    ax1.set_ylabel("paper metric (mean reward per agent per episode)")
    ax1.legend(fontsize=8)
    ax2.legend(fontsize=8)
    fig.suptitle("Trained HAMMER teams under message faults (cn3)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
