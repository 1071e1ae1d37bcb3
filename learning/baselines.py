"""What a run's final number means: reference points per preset, printed by `hammer train` and
`hammer up` at the end of a run, so a newcomer can tell a learned team from one that learned nothing.

The table is data with its source on every row; change a row only together with its source.
`random play` is uniform random actions through the same env and metric (measured with
`make_vec_env`, seed 0, 8 copies: 2,000 episodes on cn, 200 on mw); `IL` is the finished
independent-learners result of docs/results (mean over seeds of the last 500 episodes).
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from typing import Any

# preset, reference, paper metric, episodes behind it, source
_TABLE = """\
cn3,random play,-26.67,2000,uniform random actions (seed 0)
cn3,IL,-16.00,30000,docs/results/cn3-table.md (5 seeds)
cn5,random play,-35.37,2000,uniform random actions (seed 0)
cn5,IL,-26.81,30000,docs/results/cn5-table.md (5 seeds)
mw3,random play,-101.12,200,uniform random actions (seed 0)
mw3,IL,-40.08,10000,docs/results/mw3-table.md (5 seeds)
mw5,random play,-102.94,200,uniform random actions (seed 0)
mw5,IL,-84.62,2000,docs/results/mw5-pilot-table.md (3-seed pilot)
rware-tiny-2ag,random play,0.04,600,uniform random actions (docs/results/warehouse-random-floor.json)
rware-tiny-4ag,random play,0.14,600,uniform random actions (docs/results/warehouse-random-floor.json)
"""
# No IL row for the warehouse presets yet: their pilot (docs/results/warehouse.md) has no finished
# comparison; a row comes with its source.
PAPER_PRESETS = ("cn3", "cn5", "mw3", "mw5")


@dataclass(frozen=True)
class Baseline:
    preset: str
    reference: str
    metric: float
    episodes: int
    source: str


def baselines() -> list[Baseline]:
    rows = csv.reader(io.StringIO(_TABLE))
    return [Baseline(p, r, float(m), int(e), s) for p, r, m, e, s in rows]


def preset_of(cfg: Any) -> str | None:
    """The preset whose env a config runs (same env, team size and env kwargs), else None."""
    from hammer.learning.config import PRESETS, preset_dict

    for name in PRESETS:
        p = preset_dict(name)
        if (p.get("env"), p.get("n_agents"), p.get("env_kwargs") or {}) == (cfg.env, cfg.n_agents,
                                                                            cfg.env_kwargs or {}):
            return name
    return None


def in_context(cfg: Any, metric: float) -> str | None:
    """One line placing `metric` among the preset's references, or None when the env has none."""
    preset = preset_of(cfg)
    rows = [b for b in baselines() if b.preset == preset]
    if not rows:
        return None
    refs = ", ".join(f"{b.reference} {b.metric:.2f}" + ("" if b.reference == "random play" else
                                                         f" after {b.episodes:,} episodes") for b in rows)
    return f"for scale on {preset} (higher is better): {refs}; this run {metric:.2f}"
