"""Why did a run fall back after it had learned? Each run's curve next to its local learner's
policy entropy, approximate KL and clip fraction, and a table comparing those before and after
the run's best rolling mean.

One line per run (not a seed mean): the question is about individual runs, and averaging seeds
that peak at different times would hide exactly the fall-back being looked at.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from hammer.experiments.plot import save_figure
from hammer.experiments.report import final_performance
from hammer.experiments.runs import Run, best_rolling, rolling_mean
from hammer.experiments.train_stats import load_train_stats

Stats = dict[str, tuple[np.ndarray, np.ndarray]]  # load_train_stats: {tag: (episodes, values)}

# (tag, axis label): the local agents' learner; every variant has one
DIAG_STATS = (
    ("train/local/entropy", "local policy entropy"),
    ("train/local/approx_kl", "local approx. KL per update"),
    ("train/local/clipfrac", "local clip fraction"),
)


@dataclass
class Diagnosis:
    name: str
    label: str
    episodes: int
    final: float  # mean of the last `last` episodes
    best: float  # best rolling mean (complete windows only)
    best_episode: int
    # per stat tag: (value at the best episode, value at the end, median before best, median after best)
    stats: dict[str, tuple[float, float, float, float]]


def _split(episodes: np.ndarray, values: np.ndarray, at: int) -> tuple[float, float, float, float]:
    nan = float("nan")
    if len(values) == 0:
        return nan, nan, nan, nan
    i = int(np.searchsorted(episodes, at, side="right"))  # updates logged by the best episode
    at_best = float(values[i - 1]) if i > 0 else nan
    before = float(np.median(values[:i])) if i > 0 else nan
    after = float(np.median(values[i:])) if i < len(values) else nan
    return at_best, float(values[-1]), before, after


def diagnose(run: Run, window: int = 500, last: int = 500, stats: Stats | None = None) -> Diagnosis:
    """`stats`: the run's `load_train_stats`, if the caller has it already (reading TensorBoard
    events takes seconds per run)."""
    final = final_performance(run, last)  # ValueError for a run without episodes
    best, at = best_rolling(run.paper_metric, window)
    stats = load_train_stats(run.path) if stats is None else stats
    return Diagnosis(
        name=run.path.name, label=run.label, episodes=len(run.paper_metric),
        final=final, best=best, best_episode=at,
        stats={tag: _split(*stats[tag], at) for tag, _ in DIAG_STATS if tag in stats},
    )


def to_markdown(diags: list[Diagnosis], window: int, last: int) -> str:
    def f(x: float, d: int) -> str:
        return "n/a" if np.isnan(x) else f"{x:.{d}f}"

    out = [
        (f"best = best rolling-{window} mean (episode); final = mean of the last {last} episodes; "
         "entropy = the local Gaussian/categorical policy's entropy at the best episode → at the end; "
         "KL and clip fraction = medians over the updates before → after the best episode; "
         "– = no learner statistics kept for this run."),
        "",
        "| run | variant | episodes | best (episode) | final | entropy | approx. KL | clip fraction |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for d in diags:
        ent, kl, cf = (d.stats.get(t) for t, _ in DIAG_STATS)
        cells = [
            f"{f(ent[0], 2)} → {f(ent[1], 2)}" if ent else "–",
            f"{f(kl[2], 4)} → {f(kl[3], 4)}" if kl else "–",
            f"{f(cf[2], 3)} → {f(cf[3], 3)}" if cf else "–",
        ]
        out.append(f"| {d.name} | {d.label} | {d.episodes} | {d.best:.2f} ({d.best_episode}) | {d.final:.2f} | "
                   + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


def plot_diagnostics(runs: list[Run], out: Path, window: int = 500,
                     stats: dict[Path, Stats] | None = None) -> list[Path]:
    """Write `<out>.png` and `<out>.svg`: the rolling paper metric and each DIAG_STATS statistic
    against episodes, one line per run (colour = variant, dash = seed, a dot at the run's best point).
    `stats`: {run path: its load_train_stats} if the caller has them already."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = sorted({r.label for r in runs})
    colour = {lab: plt.get_cmap("tab10")(i % 10) for i, lab in enumerate(labels)}
    fig, axes = plt.subplots(1 + len(DIAG_STATS), 1, figsize=(9, 2.6 * (1 + len(DIAG_STATS))), sharex=True)
    dashes = ["-", "--", ":", "-.", (0, (5, 1, 1, 1, 1, 1))]
    for r in sorted(runs, key=lambda r: (r.label, r.seed)):
        c, ls = colour[r.label], dashes[r.seed % len(dashes)]
        best, at = best_rolling(r.paper_metric, window)
        axes[0].plot(np.arange(1, len(r.paper_metric) + 1), rolling_mean(r.paper_metric, window), color=c, ls=ls,
                     lw=1, label=f"{r.label} s{r.seed}")
        axes[0].plot([at], [best], "o", color=c, ms=4)
        run_stats = stats[r.path] if stats is not None else load_train_stats(r.path)
        for ax, (tag, _) in zip(axes[1:], DIAG_STATS, strict=True):
            if tag in run_stats:
                ep, v = run_stats[tag][0], rolling_mean(run_stats[tag][1], 25)
                ax.plot(ep, v, color=c, ls=ls, lw=1)
                i = int(np.searchsorted(ep, at, side="right"))
                if i > 0:
                    ax.plot([ep[i - 1]], [v[i - 1]], "o", color=c, ms=4)
    axes[0].set_ylabel(f"paper metric\n(rolling {window})")
    axes[0].legend(fontsize=7, ncol=2)
    for ax, (_, name) in zip(axes[1:], DIAG_STATS, strict=True):
        ax.set_ylabel(f"{name}\n(rolling 25 updates)")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("episode")
    fig.tight_layout()
    return save_figure(fig, out, dpi=110)
