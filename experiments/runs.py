"""Reading finished (or partial) run directories written by `hammer train` / `hammer up`.

A run directory holds `config.json` (the resolved RunConfig), `metrics.csv` (one row per
episode) and, once finished, `summary.json`. Everything here reads only those files, so curves
and tables can be rebuilt from runs made on any machine.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from hammer.experiments.archive import METRICS_NPZ, PARTIAL, load_metrics_npz
from hammer.experiments.metrics_csv import read_metrics_csv

# Fields that never make two runs different comparisons: the seed, the fields `Run.label` shows
# (variant, central mode, central network, message length) and those that change speed or bookkeeping, not learning.
_NOT_SETTING = frozenset({"env", "n_agents", "seed", "variant", "central_mode", "central_net", "msg_dim", "out",
                          "env_workers", "env_parent_slice", "torch_threads", "compile", "checkpoint_every"})


@functools.cache
def _reference(env: str, n_agents: int) -> dict:
    """The resolved config of a run of this env and N with nothing overridden: its paper preset
    (cn3, cn5, mw3, mw5), or RunConfig's defaults for any other env and N."""
    from hammer.learning.config import merge_config
    from hammer.learning.presets import PRESETS

    preset = next((p for p, d in PRESETS.items() if d["env"] == env and d["n_agents"] == n_agents), None)
    return merge_config(preset=preset, extra={"env": env, "n_agents": n_agents}).model_dump(mode="json")


def setting_changes(config: dict) -> list[str]:
    """`field=value` for every field of `config` that differs from its reference, by
    `learning.config.config_changes` (nested as `env_kwargs.field=value`), minus `_NOT_SETTING`."""
    from hammer.learning.config import config_changes

    try:
        ref = _reference(config.get("env"), config.get("n_agents"))
    except (ValueError, TypeError):  # no config can be built for this env and N today: nothing to compare
        return []

    return [f"{key}={json.dumps(value)}" for key, value in config_changes(config, ref, _NOT_SETTING).items()]


@dataclass
class Run:
    path: Path
    config: dict
    episodes: np.ndarray  # (E,) episode number
    paper_metric: np.ndarray  # (E,) the paper's average reward per local agent
    team_return: np.ndarray  # (E,)
    finished: bool

    @property
    def seed(self) -> int:
        return int(self.config.get("seed", 0))

    @property
    def setting(self) -> str:
        """The row group of tables and the panel of plots: env and N, plus every field this run
        changed from its paper preset, e.g. `cn N=3 (gae_lambda=1.0, minibatches=1)`. Runs that
        differ in anything but the seed and the label's fields are never pooled as seeds."""
        base = f"{self.config.get('env', '?')} N={self.config.get('n_agents', '?')}"
        changed = setting_changes(self.config)
        return f"{base} ({', '.join(changed)})" if changed else base

    @property
    def label(self) -> str:
        """The comparison a run belongs to: variant, central mode for HAMMER (+ `-set` with the set
        central network), message length."""
        variant = self.config.get("variant", "?")
        if variant == "hammer":
            net = "-set" if self.config.get("central_net", "concat") == "set" else ""
            return f"hammer-{self.config.get('central_mode', '?')}{net}-m{self.config.get('msg_dim', '?')}"
        if variant == "random":
            return f"random-m{self.config.get('msg_dim', '?')}"
        return str(variant)


def find_runs(paths: list[Path]) -> list[Path]:
    """Every run directory (holding metrics.csv) or archived run (metrics.npz, see
    `experiments.archive`) at or below the given paths. Snapshots of runs in progress
    (`<archive>/_partial/`) are never results: they are skipped, even when named directly."""
    found: list[Path] = []
    for p in paths:
        p = Path(p)
        if not p.exists():
            raise FileNotFoundError(f"run path {p} does not exist")
        if PARTIAL in p.resolve().parts:
            continue
        if (p / "metrics.csv").is_file() or (p / METRICS_NPZ).is_file():
            found.append(p)
        else:
            found.extend(sorted({m.parent for m in [*p.rglob("metrics.csv"), *p.rglob(METRICS_NPZ)]
                                 if PARTIAL not in m.relative_to(p).parts}))
    return found


def load_run(path: Path) -> Run:
    path = Path(path)
    cfg_file = path / "config.json"
    if not cfg_file.is_file():
        raise FileNotFoundError(f"{path} has no config.json: not a hammer run directory")
    config = json.loads(cfg_file.read_text())
    if not (path / "metrics.csv").is_file() and (path / METRICS_NPZ).is_file():
        e, m, t = load_metrics_npz(path / METRICS_NPZ)
        return Run(path=path, config=config, episodes=e, paper_metric=m, team_return=t,
                   finished=(path / "summary.json").is_file())
    m = read_metrics_csv(path / "metrics.csv")
    return Run(path=path, config=config, episodes=m["episode"], paper_metric=m["paper_metric"],
               team_return=m["team_return"], finished=(path / "summary.json").is_file())


def rolling_mean(x: np.ndarray, window: int) -> np.ndarray:
    """Trailing rolling mean; the first window-1 points average what exists so far."""
    if len(x) == 0:
        return x
    c = np.cumsum(np.insert(np.asarray(x, dtype=np.float64), 0, 0.0))
    idx = np.arange(1, len(x) + 1)
    lo = np.maximum(idx - window, 0)
    return (c[idx] - c[lo]) / (idx - lo)


def best_rolling(metric: np.ndarray, window: int) -> tuple[float, int]:
    """(best rolling mean over complete windows, the episode it ends at); over the whole run if it
    is shorter than one window. How high a run got, where the final mean says where it ended."""
    rm = rolling_mean(metric, window)
    first = min(window, len(rm)) - 1
    i = first + int(np.argmax(rm[first:]))
    return float(rm[i]), i + 1


def group_runs(runs: list[Run]) -> dict[tuple[str, str], list[Run]]:
    """Runs grouped by (setting, label): the seeds of one comparison."""
    groups: dict[tuple[str, str], list[Run]] = {}
    for r in runs:
        groups.setdefault((r.setting, r.label), []).append(r)
    return groups
