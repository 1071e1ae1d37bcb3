"""The run directory: everything a training run leaves behind, in plain formats.

    config.json / config.yaml   the resolved RunConfig
    metrics.csv                 one row per finished episode:
                                episode, env_steps, paper_metric, team_return, length, wall_time
    tb/                         TensorBoard events (per update: losses, KL, metric, steps/s)
    checkpoints/ckpt_XXXXXXX.safetensors + .json
                                weights and optimiser states (safetensors) + counters, RNG
                                states and optimiser hyper-parameters (JSON); never pickle
    final/local.safetensors, final/central.safetensors
                                the trained policy weights as exported numpy dicts (edge devices)
    summary.json                written when the run finishes (experiments treat it as "done"),
                                with the CPU, BLAS/oneDNN versions and thread settings under "host"
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from hammer.learning.config import ConfigError, RunConfig, build_config, save_yaml
from safetensors.numpy import save_file as save_numpy

if TYPE_CHECKING:  # torch is imported where checkpoints are made: the env host never needs it
    import torch

CSV_HEADER = ["episode", "env_steps", "paper_metric", "team_return", "length", "wall_time"]


def optimizer_to_tensors(opt: torch.optim.Optimizer, prefix: str) -> tuple[dict[str, torch.Tensor], dict]:
    """Split an optimiser state dict into tensors (safetensors) and JSON-able hyper-parameters, on the
    host whatever the training device (a checkpoint resumes on any device)."""
    import torch

    sd = opt.state_dict()
    tensors, keys = {}, {}
    for pid, st in sd["state"].items():
        keys[str(pid)] = sorted(st)
        for name, val in st.items():
            tensors[f"{prefix}/{pid}/{name}"] = torch.as_tensor(val, device="cpu").detach().clone().contiguous()
    return tensors, {"param_groups": sd["param_groups"], "state_keys": keys}


def optimizer_from_tensors(opt: torch.optim.Optimizer, prefix: str, tensors: dict[str, torch.Tensor],
                           meta: dict) -> None:
    state = {int(pid): {name: tensors[f"{prefix}/{pid}/{name}"] for name in names}
             for pid, names in meta["state_keys"].items()}
    groups = [dict(g, betas=tuple(g["betas"])) if "betas" in g else g for g in meta["param_groups"]]
    opt.load_state_dict({"state": state, "param_groups": groups})


def fsync_file(path: Path) -> None:
    """Flush a written file to the disk (any fd of the file will do on Linux)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class RunDir:
    """Creates or reopens one run directory and writes its files."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.ckpt_dir = self.path / "checkpoints"
        self.metrics_path = self.path / "metrics.csv"
        self._csv_file = None
        self._csv = None
        self._tb = None

    # ----- creation -----------------------------------------------------------------------------
    @classmethod
    def create(cls, path: str | Path, cfg: RunConfig) -> RunDir:
        """A fresh run; an existing directory is accepted only if it holds no run yet (sweeps pre-create it)."""
        rd = cls(path)
        if rd.latest_checkpoint() is not None or (rd.path / "summary.json").exists():
            raise ConfigError(f"run dir '{rd.path}': already holds a run; fix: pass --resume {rd.path} "
                              "to continue it, or choose another --run-dir/--name")
        rd.path.mkdir(parents=True, exist_ok=True)
        (rd.path / "config.json").write_text(json.dumps(cfg.model_dump(mode="json"), indent=1))
        save_yaml(cfg, rd.path / "config.yaml")
        rd.truncate_metrics(0)
        return rd

    @classmethod
    def branch(cls, src: RunDir, path: str | Path, cfg: RunConfig) -> RunDir:
        """A new run at `path` that continues `src` from its latest checkpoint under `cfg` (a few
        fields changed): the checkpoint, the episodes it covers and the TensorBoard log are copied,
        `src` is not touched. Resuming it (`train(..., resume=True)`) is the branch."""
        stem = src.latest_checkpoint()
        if stem is None:
            raise ConfigError(f"--branch '{src.path}': no checkpoint yet; fix: branch a run that has one")
        rd = cls.create(path, cfg)
        rd.ckpt_dir.mkdir(parents=True, exist_ok=True)
        for suffix in (".safetensors", ".json"):  # the JSON last: it marks the pair complete
            shutil.copyfile(str(stem) + suffix, rd.ckpt_dir / (stem.name + suffix))
        shutil.copyfile(src.metrics_path, rd.metrics_path)  # resuming cuts it to the checkpoint's episodes
        if (src.path / "tb").is_dir():  # resuming purges what was logged after the checkpoint
            shutil.copytree(src.path / "tb", rd.path / "tb", dirs_exist_ok=True)
        return rd

    @classmethod
    def open(cls, path: str | Path) -> tuple[RunDir, RunConfig]:
        rd = cls(path)
        cfg_file = rd.path / "config.json"
        if not cfg_file.is_file():
            raise ConfigError(f"--resume '{rd.path}': no config.json there; fix: pass a run directory "
                              "made by `hammer train`")
        return rd, build_config(json.loads(cfg_file.read_text()))

    def write_config(self, cfg: RunConfig) -> None:
        (self.path / "config.json").write_text(json.dumps(cfg.model_dump(mode="json"), indent=1))
        save_yaml(cfg, self.path / "config.yaml")

    # ----- metrics ------------------------------------------------------------------------------
    def truncate_metrics(self, n_rows: int) -> None:
        """Keep the header and the first n_rows episodes (resume rewrites what came after)."""
        rows: list[list[str]] = []
        if n_rows and self.metrics_path.is_file():
            with open(self.metrics_path, newline="") as f:
                rows = list(csv.reader(f))[1 : n_rows + 1]
        if len(rows) != n_rows:
            raise RuntimeError(f"metrics.csv has {len(rows)} episodes, the checkpoint expects {n_rows}")
        with open(self.metrics_path, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(CSV_HEADER)
            w.writerows(rows)

    def append_episodes(self, rows: list[tuple]) -> None:
        if self._csv is None:
            self._csv_file = open(self.metrics_path, "a", newline="")  # noqa: SIM115
            self._csv = csv.writer(self._csv_file)
        self._csv.writerows(rows)

    def flush(self) -> None:
        if self._csv_file is not None:
            self._csv_file.flush()
        if self._tb is not None:
            self._tb.flush()

    # ----- TensorBoard --------------------------------------------------------------------------
    def tensorboard(self, purge_step: int | None = None):
        if self._tb is None:
            from torch.utils.tensorboard import SummaryWriter

            self._tb = SummaryWriter(str(self.path / "tb"), purge_step=purge_step)
        return self._tb

    # ----- checkpoints --------------------------------------------------------------------------
    def save_checkpoint(self, update: int, tensors: dict[str, torch.Tensor], meta: dict[str, Any],
                        keep: int = 3) -> Path:
        """Atomic-ish: the JSON (which marks a checkpoint as complete) is written last, and both
        reach the disk first (fsync), so a machine that dies cannot leave a JSON vouching for a
        lost tensor file. Tensors are written from the host: a run trained on a GPU resumes on the CPU
        and back (loading copies them onto the trainer's device: `load_state_dict`)."""
        from safetensors.torch import save_file

        self.ckpt_dir.mkdir(parents=True, exist_ok=True)
        stem = self.ckpt_dir / f"ckpt_{update:07d}"
        save_file({k: v.detach().cpu().contiguous() for k, v in tensors.items()}, str(stem) + ".safetensors")
        fsync_file(Path(str(stem) + ".safetensors"))
        tmp = Path(str(stem) + ".json.tmp")
        tmp.write_text(json.dumps(meta))
        fsync_file(tmp)
        tmp.replace(str(stem) + ".json")
        for old in sorted(self.ckpt_dir.glob("ckpt_*.json"))[:-keep]:
            old.unlink()
            old.with_suffix(".safetensors").unlink(missing_ok=True)
        return stem

    def latest_checkpoint(self) -> Path | None:
        found = sorted(self.ckpt_dir.glob("ckpt_*.json")) if self.ckpt_dir.is_dir() else []
        return found[-1].with_suffix("") if found else None

    @staticmethod
    def load_checkpoint(stem: Path) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        from safetensors.torch import load_file

        return load_file(str(stem) + ".safetensors"), json.loads(Path(str(stem) + ".json").read_text())

    # ----- results ------------------------------------------------------------------------------
    def export_policy(self, local: dict[str, np.ndarray], central: dict[str, np.ndarray] | None,
                      meta: dict[str, str]) -> None:
        d = self.path / "final"
        d.mkdir(exist_ok=True)
        save_numpy(local, str(d / "local.safetensors"), metadata=meta)
        if central is not None:
            save_numpy(central, str(d / "central.safetensors"), metadata=meta)

    def write_summary(self, summary: dict[str, Any]) -> None:
        """summary.json, with the machine's maths path (`learning.host_info`) under "host"."""
        from hammer.learning.host_info import host_info

        summary = dict(summary, written_at=time.strftime("%Y-%m-%dT%H:%M:%S"), host=host_info())
        (self.path / "summary.json").write_text(json.dumps(summary, indent=1))

    def close(self) -> None:
        if self._csv_file is not None:
            self._csv_file.close()
            self._csv_file = self._csv = None
        if self._tb is not None:
            self._tb.close()
            self._tb = None
