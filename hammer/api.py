"""hammer as a library: what a notebook or a script needs to do what the CLI does.

    import hammer

    run = hammer.train("cn3", variant="hammer", episodes=400, run_dir="runs/cn3-a")
    print(run.summary["final_paper_metric_last500"], len(run.metrics()))
    bundle = hammer.export(run.run_dir, "bundles/cn3-a")
    served = hammer.serve_bundle(bundle, episodes=64)           # the team as processes, frozen weights
    dist = hammer.up("cn3", episodes=200, secure=True)   # training as processes over Zenoh

Each call does one command's work (`hammer train`, `hammer up`, `hammer export`, `hammer serve`:
`serve_bundle`, as `hammer.serve` is the package) without its printing and returns what it made. Configuration is the CLI's: a preset, then fields
as keyword arguments (`variant="il"`, `episodes=400`), then `set=["env_kwargs.local_ratio=0.25"]`
overrides; a wrong field raises `hammer.ConfigError` naming it and the fix. `hammer.config(...)`
builds the RunConfig alone, to inspect or to pass to `train` / `up`.
"""

from __future__ import annotations

import csv
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hammer.deploy.launcher import UpResult
from hammer.learning.config import ConfigError, RunConfig
from hammer.serve.bundle import Bundle, BundleError

__all__ = ["Bundle", "BundleError", "ConfigError", "RunConfig", "TrainResult", "UpResult", "config", "export",
           "load_bundle", "serve_bundle", "train", "up"]


@dataclass
class TrainResult:
    """A finished (or resumed to its budget) `hammer train` run."""

    run_dir: Path
    config: RunConfig
    summary: dict[str, Any]

    def metrics(self) -> list[dict[str, str]]:
        """metrics.csv, one dict per episode (episode, env_steps, paper_metric, team_return, length, wall_time)."""
        with open(self.run_dir / "metrics.csv", newline="") as f:
            return list(csv.DictReader(f))


def config(preset: str | None = "cn3", *, set: Iterable[str] = (), file: str | Path | None = None,
           **fields: Any) -> RunConfig:
    """The RunConfig of a preset with `fields` and `set` overrides applied (as `hammer train` builds it)."""
    from hammer.learning.config import merge_config

    return merge_config(preset, file, list(set), fields)


def _config(preset: str | RunConfig | None, set: Iterable[str], file: str | Path | None,
            fields: dict[str, Any]) -> RunConfig:
    if isinstance(preset, RunConfig):
        if fields or list(set) or file is not None:
            raise ConfigError("a RunConfig was given together with fields or overrides; fix: build it with "
                              "hammer.config(...) including them, or pass a preset name")
        return preset
    return config(preset, set=set, file=file, **fields)


def train(preset: str | RunConfig | None = "cn3", *, run_dir: str | Path | None = None, set: Iterable[str] = (),
          file: str | Path | None = None, resume: bool = False, tensorboard: bool = False,
          **fields: Any) -> TrainResult:
    """Train one team in this process (`hammer train`). `run_dir`: where (default `out/<run name>`);
    `resume=True`: continue `run_dir` from its latest checkpoint (its own config; `episodes=` may grow)."""
    from hammer.learning.config import build_config
    from hammer.learning.run_env import check_env_fits, make_env
    from hammer.learning.rundir import RunDir
    from hammer.learning.trainer import train as run_training

    if resume:
        if run_dir is None:
            raise ConfigError("resume=True needs run_dir: the run to continue")
        rd, cfg = RunDir.open(Path(run_dir))
        if fields.get("episodes") is not None:
            cfg = build_config({**cfg.model_dump(), "episodes": fields["episodes"]})
            rd.write_config(cfg)
    else:
        cfg = _config(preset, set, file, fields)
    env = make_env(cfg)  # a bad env fails before any file is written, as with `hammer train`
    check_env_fits(cfg, env.spec)
    if not resume:
        rd = RunDir.create(Path(run_dir) if run_dir is not None else Path(cfg.out) / cfg.run_name(), cfg)
    try:
        summary = run_training(cfg, rd, resume=resume, env=env, tensorboard=tensorboard)
    finally:
        rd.close()
    return TrainResult(rd.path, cfg, summary)


def up(preset: str | RunConfig | None = "cn3", *, run_dir: str | Path | None = None, set: Iterable[str] = (),
       file: str | Path | None = None, secure: bool = False, runtime: dict[str, Any] | None = None,
       **fields: Any) -> UpResult:
    """Train one team as separate processes over Zenoh on this host (`hammer up`); `runtime`:
    RuntimeSettings fields (deadlines, faults, chaos, ...). Raises `hammer.deploy.launcher.UpError` when a
    role fails or the run stops before its budget."""
    from hammer.deploy.launcher import launch
    from hammer.runtime.settings import build_settings

    cfg = _config(preset, set, file, fields)
    path = Path(run_dir) if run_dir is not None else Path(cfg.out) / f"up-{cfg.run_name()}-{time.strftime('%Y%m%d-%H%M%S')}"
    settings = build_settings({"run_id": path.name.replace("_", "-")[:64], **(runtime or {})},
                              fixed={"secure": True} if secure else None, flag="runtime")
    return launch(cfg, settings, path)


def export(run_dir: str | Path, out: str | Path, *, force: bool = False) -> Bundle:
    """A self-contained bundle of a finished run's team (`hammer export`)."""
    from hammer.serve.bundle import export_bundle

    return export_bundle(Path(run_dir), Path(out), force=force)


def load_bundle(path: str | Path) -> Bundle:
    """A bundle made by `export`, checked (manifest, sha256 of every file, weight shapes)."""
    from hammer.serve.bundle import load_bundle as load

    return load(Path(path))


def serve_bundle(bundle: Bundle | str | Path, *, episodes: int = 100, run_dir: str | Path | None = None,
          runtime: Iterable[str] = (), seed: int | None = None) -> UpResult:
    """Run a trained team as processes with frozen weights and no learner (`hammer serve`);
    `runtime`: RuntimeSettings items as on the command line (`"msg_deadline_ms=20"`)."""
    from hammer.deploy.launcher import launch
    from hammer.deploy.plan import plan_serve

    p = plan_serve(bundle.path if isinstance(bundle, Bundle) else Path(bundle), episodes=episodes, seed=seed,
                   runtime=list(runtime), run_dir=None if run_dir is None else Path(run_dir))
    return launch(p.cfg, p.settings, p.run_dir)
