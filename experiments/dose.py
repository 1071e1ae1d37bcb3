"""The dose-response analysis of docs/results/plan-dose-response.md: at each level of hidden
information (`env_kwargs.obs_radius`), Δ = IQM(variant) − IQM(IL) of the runs' final values with a
bootstrap CI, and the least-squares slope of Δ against the fraction hidden h(r) with a stratified
bootstrap CI (each variant × level cell's seeds resampled on their own, the slope recomputed).

The x-axis h(r) is fixed before any training (`envs.local_view.spread_hidden_fraction`): the
fraction of relative-position slots the radius hides under random play.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from hammer.experiments.report import area_under_curve, final_performance
from hammer.experiments.runs import Run
from hammer.experiments.stats import REPS, SEED, iqm, iqm_difference_ci, welch_p


@dataclass
class Level:
    radius: float | None  # None: the full view
    hidden: float  # h(r)
    variant: str
    n: int
    n_il: int
    delta: float
    lo: float
    hi: float
    p: float | None


@dataclass
class Slope:
    variant: str
    slope: float
    lo5: float  # one-sided 95 % lower bound (5th percentile)
    lo: float  # two-sided 95 % CI
    hi: float


def run_radius(run: Run) -> float | None:
    r = (run.config.get("env_kwargs") or {}).get("obs_radius")
    return None if r is None else float(r)


def _label_matches(label: str, name: str) -> bool:
    return label == name or label.startswith(name + "-m")


def cells(runs: list[Run], measure: str = "final", last: int = 500, auc: int = 10000
          ) -> dict[tuple[float | None, str], np.ndarray]:
    """(radius, label) -> the runs' values (final: mean of the last `last` episodes; auc: mean of
    the first `auc`)."""
    out: dict[tuple[float | None, str], list[float]] = {}
    for r in runs:
        v = final_performance(r, last) if measure == "final" else area_under_curve(r, auc)
        out.setdefault((run_radius(r), r.label), []).append(v)
    return {k: np.array(v) for k, v in out.items()}


def _hidden(radius: float | None) -> float:
    from hammer.envs.local_view import spread_hidden_fraction

    return 0.0 if radius is None else spread_hidden_fraction(radius)


def learned_hidden(run: Run, episodes: int = 100, seed: int = 0) -> float:
    """The fraction of relative-position slots the run's radius hides while its trained team plays
    (evaluation seed `seed`, its first `episodes` episodes, the runtime's acting): the plan's
    exploratory companion of the fixed random-play h (trained agents sit nearer their landmarks)."""
    from hammer.envs.local_view import hidden_fraction
    from hammer.experiments.messages import TeamActor

    radius = run_radius(run)
    if radius is None:
        return 0.0
    rec = TeamActor(run.path, need_messages=False).rollout(seed, episodes, record=True)
    return hidden_fraction(rec.full_obs, radius, rec.full_obs.shape[2])


def learned_hidden_table(runs: list[Run], episodes: int = 100) -> str:
    """Per level: h under random play (the plan's x-axis) and under each variant's trained teams."""
    got: dict[tuple[float | None, str], list[float]] = {}
    for r in runs:
        if (r.path / "final").is_dir() and r.config.get("variant") != "centralized":  # it sees everything
            got.setdefault((run_radius(r), r.label), []).append(learned_hidden(r, episodes))
    labels = sorted({lab for _, lab in got})
    radii = sorted({rad for rad, _ in got}, key=lambda x: -np.inf if x is None else -x)  # full view first
    lines = [(f"Exploratory (plan-dose-response.md): fraction of relative-position slots hidden, under random play "
             f"(the plan's fixed h) and while each variant's trained teams play (evaluation seed 0, first {episodes} "
             "episodes; mean ± s.e. over teams)."), "",
             "| obs_radius | h, random play | " + " | ".join(labels) + " |",
             "| --- | ---: | " + " | ".join("---:" for _ in labels) + " |"]
    for rad in radii:
        row = [("full" if rad is None else f"{rad:g}"), f"{_hidden(rad):.3f}"]
        for lab in labels:
            v = np.array(got.get((rad, lab), []))
            se = v.std(ddof=1) / np.sqrt(len(v)) if len(v) > 1 else 0.0
            row.append(f"{v.mean():.3f} ± {se:.3f}" if len(v) else "")
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"


def dose_levels(values: dict[tuple[float | None, str], np.ndarray], variant: str, baseline: str = "il"
                ) -> list[Level]:
    """Δ per level for `variant` (a name like hammer-rl, matching any message length) vs baseline."""
    radii = sorted({r for r, _ in values}, key=lambda r: (0, 0.0) if r is None else (1, -r))  # full view first
    out = []
    for r in radii:
        a = [v for (rr, lb), v in values.items() if rr == r and _label_matches(lb, variant)]
        b = [v for (rr, lb), v in values.items() if rr == r and _label_matches(lb, baseline)]
        if len(a) != 1 or len(b) != 1:
            continue
        d, lo, hi = iqm_difference_ci(a[0], b[0])
        out.append(Level(r, _hidden(r), variant, len(a[0]), len(b[0]), d, lo, hi, welch_p(a[0], b[0])))
    return out


def dose_slope(values: dict[tuple[float | None, str], np.ndarray], variant: str, baseline: str = "il",
               reps: int = REPS, seed: int = SEED) -> Slope | None:
    """Least-squares slope of Δ(r) on h(r) over the levels, with its stratified-bootstrap CI."""
    levels = dose_levels(values, variant, baseline)
    if len(levels) < 2:
        return None
    h = np.array([lv.hidden for lv in levels])
    rng = np.random.default_rng(seed)
    deltas = np.empty((reps, len(levels)))
    for j, lv in enumerate(levels):
        a = next(v for (rr, lb), v in values.items() if rr == lv.radius and _label_matches(lb, variant))
        b = next(v for (rr, lb), v in values.items() if rr == lv.radius and _label_matches(lb, baseline))
        ra = a[rng.integers(0, len(a), (reps, len(a)))]
        rb = b[rng.integers(0, len(b), (reps, len(b)))]
        deltas[:, j] = iqm(ra, axis=1) - iqm(rb, axis=1)
    hc = h - h.mean()
    slopes = (deltas - deltas.mean(axis=1, keepdims=True)) @ hc / (hc @ hc)
    point = float(np.array([lv.delta for lv in levels]) @ hc / (hc @ hc))
    lo5, lo, hi = np.percentile(slopes, [5, 2.5, 97.5])
    return Slope(variant, point, float(lo5), float(lo), float(hi))


def to_markdown(levels: list[Level], slopes: list[Slope], measure: str) -> str:
    out = [(f"Dose-response ({measure}): Δ = IQM(variant) − IQM(IL) at each obs_radius level, 95 % bootstrap CI, "
           "Welch p (uncorrected; Holm across the plan's family is in the report of the same runs); "
           "h = fraction of relative-position slots hidden under random play."), "",
           "| variant | obs_radius | h | seeds (variant / IL) | Δ [95% CI] | p (Welch) |",
           "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for lv in levels:
        r = "full" if lv.radius is None else f"{lv.radius:g}"
        p = "" if lv.p is None else f"{lv.p:.3g}"
        out.append(f"| {lv.variant} | {r} | {lv.hidden:.3f} | {lv.n} / {lv.n_il} | {lv.delta:+.2f} "
                   f"[{lv.lo:+.2f}, {lv.hi:+.2f}] | {p} |")
    out += ["", "| variant | slope of Δ on h | one-sided 95 % lower bound | 95 % CI |", "| --- | ---: | ---: | ---: |"]
    for s in slopes:
        out.append(f"| {s.variant} | {s.slope:+.2f} | {s.lo5:+.2f} | [{s.lo:+.2f}, {s.hi:+.2f}] |")
    return "\n".join(out) + "\n"


def plot_dose(levels: list[Level], out: Path) -> list[Path]:
    """Δ against h with CI bars, one line per variant."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from hammer.experiments.plot import save_figure

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for variant in sorted({lv.variant for lv in levels}):
        ls = sorted((lv for lv in levels if lv.variant == variant), key=lambda lv: lv.hidden)
        x = np.array([lv.hidden for lv in ls])
        y = np.array([lv.delta for lv in ls])
        err = np.array([[lv.delta - lv.lo for lv in ls], [lv.hi - lv.delta for lv in ls]])
        ax.errorbar(x, y, yerr=err, marker="o", capsize=3, label=f"{variant} − il")
    ax.axhline(0.0, color="grey", lw=0.8)
    ax.set_xlabel("fraction of landmarks and agents hidden from a local agent (random play)")
    ax.set_ylabel("Δ final (IQM over seeds) against IL")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return save_figure(fig, out, dpi=120)
