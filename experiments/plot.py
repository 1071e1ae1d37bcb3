"""Learning curves like the paper's figures: rolling mean of the paper metric against episodes,
one line per variant, one panel per setting; the line and band are the mean over seeds with a
standard-error band (`band="se"`, the default) or the interquartile mean with a 95 % bootstrap CI
over seeds (`band="iqm"`, experiments.stats)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from hammer.experiments.runs import Run, group_runs, rolling_mean


def seed_curves(runs: list[Run], window: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(episodes, mean, standard error) over seeds, cut to the shortest seed."""
    n = min(len(r.paper_metric) for r in runs)
    curves = np.stack([rolling_mean(r.paper_metric[:n], window) for r in runs])
    mean = curves.mean(axis=0)
    se = curves.std(axis=0, ddof=1) / np.sqrt(len(runs)) if len(runs) > 1 else np.zeros(n)
    return np.arange(1, n + 1), mean, se


def first_plotted(window: int, n: int) -> int:
    """The episode index where a curve starts being drawn: where the rolling mean holds a tenth of
    its window. Before that it averages a handful of episodes, and one run's first episode would
    draw a spike at episode 0."""
    return min(window, n) // 10


def plotted_curve(runs: list[Run], window: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`seed_curves` from `first_plotted` on."""
    x, mean, se = seed_curves(runs, window)
    skip = first_plotted(window, len(x))
    return x[skip:], mean[skip:], se[skip:]


BANDS = ("se", "iqm")


def seed_band(runs: list[Run], window: int, band: str, stride_to: int = 3000
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(episodes, centre, low, high) over seeds, every `len // stride_to`-th point."""
    if band not in BANDS:
        raise ValueError(f"band must be one of {', '.join(BANDS)}, got {band!r}")
    x, mean, se = plotted_curve(runs, window)
    stride = max(1, len(x) // stride_to)  # a smoothed curve loses nothing; keeps the SVG small
    if band == "se":
        x, mean, se = x[::stride], mean[::stride], se[::stride]
        return x, mean, mean - se, mean + se
    from hammer.experiments.stats import iqm_band

    n = len(seed_curves(runs, window)[0])
    skip = first_plotted(window, n)
    curves = np.stack([rolling_mean(r.paper_metric[:n], window)[skip:][::stride] for r in runs])
    centre, lo, hi = iqm_band(curves)
    return x[::stride], centre, lo, hi


def plot_runs(runs: list[Run], out: Path, window: int = 500, title: str | None = None, band: str = "se"
              ) -> list[Path]:
    """Write `<out>.png` and `<out>.svg`; returns the paths written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = group_runs(runs)
    settings = sorted({s for s, _ in groups})
    fig, axes = plt.subplots(1, len(settings), figsize=(6.5 * len(settings), 4.5), squeeze=False)
    for ax, setting in zip(axes[0], settings, strict=True):
        for (s, label), rs in sorted(groups.items()):
            if s != setting:
                continue
            x, centre, lo, hi = seed_band(rs, window, band)
            (line,) = ax.plot(x, centre, label=f"{label} ({len(rs)} seed{'s' if len(rs) != 1 else ''})", lw=1.4)
            ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.2, lw=0)
        ax.set_title((title or setting) + ("" if band == "se" else "\nIQM over seeds, 95% bootstrap CI"))
        ax.set_xlabel("episode")
        ax.set_ylabel(f"average reward per local agent (rolling mean {window})")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    return save_figure(fig, out, dpi=120)


def save_figure(fig, out: Path, dpi: int) -> list[Path]:
    """Write `<out>.png` and `<out>.svg` and close the figure; returns the paths written. The same
    data gives the same bytes (no date in the metadata, fixed SVG ids), so redrawing every figure
    (`make paper-report`) changes in git only the figures whose runs changed."""
    import matplotlib.pyplot as plt

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    written = []
    for ext in (".png", ".svg"):
        p = out.with_suffix(ext)
        with plt.rc_context({"svg.hashsalt": "hammer"}):
            fig.savefig(p, dpi=dpi, metadata={"Date": None} if ext == ".svg" else None)
        written.append(p)
    plt.close(fig)
    return written
