"""`hammer train --seeds 0-7`: many seeds of one setting in one process (`learning.seed_batch`)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from hammer.commands.common import fail


def train_seeds_command(seeds: str, preset: str | None, variant: str | None, central_mode: str | None,
                        episodes: int | None, config: Path | None, overrides: list[str], out: str | None,
                        name: str | None, conflicts: dict[str, Any], quiet: bool) -> None:
    from rich.console import Console

    from hammer.learning.config import ConfigError, merge_config
    from hammer.learning.rundir import RunDir
    from hammer.learning.seed_batch import parse_seeds, train_seeds

    try:
        used = [flag for flag, value in conflicts.items() if value is not None]
        if used:
            raise ConfigError(f"--seeds: cannot be combined with {used[0]} (each seed gets its own run directory "
                              "under --out); fix: drop it, and resume a seed alone with --resume RUN_DIR")
        extra: dict[str, Any] = {"variant": variant, "central_mode": central_mode, "episodes": episodes, "out": out}
        if "HAMMER_TORCH_THREADS" in os.environ and not any(s.startswith("torch_threads") for s in overrides):
            extra["torch_threads"] = int(os.environ["HAMMER_TORCH_THREADS"])
        cfgs = [merge_config(preset, config, overrides, {**extra, "seed": s}) for s in parse_seeds(seeds)]
        paths = [Path(c.out) / (f"{name}-s{c.seed}" if name else c.run_name()) for c in cfgs]
        _check_env(cfgs[0])  # the seeds share everything but the seed: one env tells for all, before any write
        dirs = [RunDir.create(p, c) for p, c in zip(paths, cfgs, strict=True)]
    except ConfigError as e:
        fail(str(e))
    console = Console(stderr=True)
    console.print(f"{len(cfgs)} seeds as one batch ({cfgs[0].env} N={cfgs[0].n_agents}, {cfgs[0].wiring.label}): "
                  f"{', '.join(str(p) for p in paths)}")
    last = [0]

    def report(p) -> None:  # a line every ~5% (seed batches run unattended)
        if p.episodes - last[0] >= max(1, p.budget // 20):
            last[0] = p.episodes
            console.print(f"episodes {p.episodes}/{p.budget} per seed  env-steps/s (all seeds) "
                          f"{p.steps_per_s * len(cfgs):,.0f}  metric(100, first seed) {p.running_metric:.2f}")

    summaries = train_seeds(cfgs, dirs, on_progress=None if quiet else report)
    for path, sm in zip(paths, summaries, strict=True):
        console.print(f"done: {_final(sm)} -> {path}")


def _final(summary: dict) -> str:
    n = summary["episodes"]
    return f"{n} episodes, last-{min(500, n)} paper metric {summary['final_paper_metric_last500']:.3f}"


def _check_env(cfg) -> None:
    """Build the env once and check it fits the config, so a bad env name or kwarg fails in one line
    before any run directory exists (as a solo `hammer train` does)."""
    from hammer.envs.registry import EnvConfigError
    from hammer.learning.config import ConfigError
    from hammer.learning.run_env import check_env_fits, make_env
    from hammer.learning.team import torch_device

    torch_device(cfg)  # and a device torch cannot use
    try:
        env = make_env(cfg)
    except EnvConfigError as e:
        raise ConfigError(str(e)) from None
    try:
        check_env_fits(cfg, env.spec)
    except EnvConfigError as e:
        raise ConfigError(str(e)) from None
    finally:
        env.close()


def main(argv: list[str]) -> int:
    """`python -m hammer.commands.seeds RUN_DIR...`: train run directories that hold only their config
    (as `hammer sweep` creates them) as one seed batch. Exit status 0 when every seed finished."""
    from hammer.learning.config import ConfigError
    from hammer.learning.rundir import RunDir
    from hammer.learning.seed_batch import train_seeds

    if not argv:
        print("error: usage: python -m hammer.commands.seeds RUN_DIR... (fresh run directories with a config.json)")
        return 2
    try:
        opened = [RunDir.open(p) for p in argv]
        summaries = train_seeds([c for _, c in opened], [rd for rd, _ in opened], tensorboard=True)
    except ConfigError as e:
        print(f"error: {e}")
        return 2
    for path, sm in zip(argv, summaries, strict=True):
        print(f"done: {_final(sm)} -> {path}")
    return 0


if __name__ == "__main__":
    import sys

    sys.exit(main(sys.argv[1:]))
