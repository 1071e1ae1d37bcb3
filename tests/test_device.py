"""`device` (RunConfig): the training code is device-agnostic, checked on the CPU (CI has no GPU).

On a GPU a forgotten device shows as a CPU tensor meeting a CUDA one. On the CPU the same mistake is
made visible by training with `device="cpu"` named explicitly while torch's default device is
`meta`: a tensor the code creates without naming its device lands on `meta`, and the first op that
mixes it with the run's CPU tensors raises (a meta tensor holds no data, so a `.numpy()` of one
raises too; nothing can quietly go on). Arrays turned into tensors (`torch.from_numpy`) are on the
CPU whatever the default, so that half of the contract, host arrays in with `.to(device)` and out
with `.cpu()`, is checked on the source instead.
"""

from __future__ import annotations

import ast
import contextlib
import csv
import json
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch
from hammer.learning.config import ConfigError, merge_config
from hammer.learning.rundir import RunDir
from hammer.learning.seed_batch import train_seeds
from hammer.learning.trainer import Trainer, train
from typer.testing import CliRunner

from tests.runtime_helpers import COMPILE_NETS

ROOT = Path(__file__).resolve().parents[1]
# 4 copies x 25-step episodes: 4 episodes per update, a checkpoint at every one
SMALL = ["num_envs=4", "rollout_steps=25", "epochs=2", "minibatches=2", "checkpoint_every=1", "device=cpu"]
VARIANTS = [("hammer", "rl"), ("hammer", "backprop"), ("il", "rl"), ("random", "rl"), ("centralized", "rl")]


@contextlib.contextmanager
def default_device_meta() -> Iterator[None]:
    torch.set_default_device("meta")
    try:
        yield
    finally:
        torch.set_default_device(None)


def _cfg(variant: str, mode: str, episodes: int, extra: list[str] | None = None, seed: int = 0):
    return merge_config("cn3", overrides=SMALL + (extra or []) + [f"variant={variant}", f"central_mode={mode}",
                                                                  f"episodes={episodes}", f"seed={seed}"])


def _rows(path: Path) -> list[list[str]]:
    with open(path / "metrics.csv", newline="") as f:
        return [r[:5] for r in csv.reader(f)]  # without the wall time


@pytest.mark.parametrize(("variant", "mode"), VARIANTS)
def test_training_and_resume_name_their_device(tmp_path: Path, variant: str, mode: str) -> None:
    """Acting, the update, a checkpoint and its resume, all with no tensor off `cfg.device`; the
    resumed run is still bit-exactly the uninterrupted one."""
    cfg = _cfg(variant, mode, 24)
    train(cfg, RunDir.create(tmp_path / "full", cfg), tensorboard=False)
    cfg = _cfg(variant, mode, 12)
    cut = RunDir.create(tmp_path / "cut", cfg)
    with default_device_meta():
        train(cfg, cut, tensorboard=False)
        rd, cfg = RunDir.open(tmp_path / "cut")
        train(cfg.model_copy(update={"episodes": 24}), rd, resume=True, tensorboard=False)
    assert len(_rows(tmp_path / "cut")) == 25 and _rows(tmp_path / "cut") == _rows(tmp_path / "full")


@pytest.mark.parametrize(("variant", "mode"), [("hammer", "rl"), ("hammer", "backprop"), ("centralized", "rl")])
def test_seed_batch_names_its_device(tmp_path: Path, variant: str, mode: str) -> None:
    cfgs = [_cfg(variant, mode, 12, seed=s) for s in (0, 1)]
    dirs = [RunDir.create(tmp_path / str(c.seed), c) for c in cfgs]
    with default_device_meta():
        summaries = train_seeds(cfgs, dirs, tensorboard=False)
    assert [s["episodes"] for s in summaries] == [12, 12]


MW = ["num_envs=2", "rollout_steps=60", "checkpoint_every=1", "epochs=2", "device=cpu", "variant=hammer",
      "episodes=4"]


def test_gaussian_actions_masked_losses_and_the_set_network_name_their_device(tmp_path: Path) -> None:
    """Multiwalker (continuous actions, walkers dropping out, seeds of a batch finishing apart) alone
    and as a seed batch, and cn3 with the attention central network."""
    mw = [merge_config("mw3", overrides=[*MW, f"seed={s}"]) for s in (0, 1)]
    cn_set = _cfg("hammer", "rl", 12, ["central_net=set"])
    with default_device_meta():
        assert train(mw[0], RunDir.create(tmp_path / "mw", mw[0]), tensorboard=False)["episodes"] == 4
        dirs = [RunDir.create(tmp_path / f"mw-b{c.seed}", c) for c in mw]
        assert [s["episodes"] for s in train_seeds(mw, dirs, tensorboard=False)] == [4, 4]
        assert train(cn_set, RunDir.create(tmp_path / "set", cn_set), tensorboard=False)["episodes"] == 12


@pytest.mark.slow
def test_compiled_update_names_its_device(tmp_path: Path) -> None:
    """compile=true: the Adam state the compiled step creates, and the graph's inputs (one compile)."""
    cfg = _cfg("hammer", "rl", 12, ["compile=true", *COMPILE_NETS])
    with default_device_meta():
        summary = train(cfg, RunDir.create(tmp_path / "c", cfg), tensorboard=False)
    assert summary["episodes"] == 12


def _learning_modules() -> list[Path]:
    return sorted((ROOT / "learning").glob("*.py"))


def test_host_arrays_cross_to_the_device_and_back_explicitly() -> None:
    """Every `torch.from_numpy(...)` in learning/ is moved on at once (`.to(...)`) and every
    `.numpy()` is of a `.cpu()`: what the meta run cannot see, since both are no-ops on the CPU."""
    bad = []
    for path in _learning_modules():
        tree = ast.parse(path.read_text())
        moved, hosted = set(), set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
                inner = node.func.value
                if node.func.attr == "to" and isinstance(inner, ast.Call):
                    moved.add(id(inner))
                if node.func.attr == "numpy" and isinstance(inner, ast.Call) and isinstance(inner.func, ast.Attribute) \
                        and inner.func.attr == "cpu":
                    hosted.add(id(node))
        for node in ast.walk(tree):
            if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)):
                continue
            where = f"{path.relative_to(ROOT)}:{node.lineno}"
            if node.func.attr == "from_numpy" and id(node) not in moved:
                bad.append(f"{where}: torch.from_numpy(...) without .to(device)")
            if node.func.attr == "numpy" and not node.args and id(node) not in hosted:
                bad.append(f"{where}: .numpy() of a tensor not first brought to the host (.cpu())")
    assert bad == []


@pytest.mark.skipif(torch.cuda.is_available(), reason="this torch sees a CUDA device")
def test_cuda_without_a_gpu_fails_at_construction_naming_the_fix(tmp_path: Path) -> None:
    cfg = _cfg("hammer", "rl", 12, ["device=cuda"])
    with pytest.raises(ConfigError) as err:
        Trainer(cfg, RunDir(tmp_path / "never"))
    msg = str(err.value)
    assert msg.startswith("config field 'device': device=cuda: torch sees no CUDA device")
    assert "torch.cuda.is_available() is False" in msg and msg.endswith("fix: --set device=cpu")
    assert not (tmp_path / "never").exists()

    from hammer.cli import app

    runner = CliRunner()
    for seeds in ([], ["--seeds", "0-1"]):
        res = runner.invoke(app, ["train", "--preset", "cn3", "--set", "device=cuda", "--episodes", "8",
                                  "--out", str(tmp_path / "cli"), "--quiet", *seeds])
        assert res.exit_code == 2 and "fix: --set device=cpu" in res.output, res.output
    assert not (tmp_path / "cli").exists()  # nothing written, no env started
    res = runner.invoke(app, ["train", "--preset", "cn3", "--set", "device=gpu", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "'device'" in res.output and "fix: use cpu, cuda or cuda:N" in res.output


def test_a_run_resumes_on_another_device(tmp_path: Path) -> None:
    """A run whose config says cuda (trained on a GPU) continues on a machine without one with
    `--resume RUN --set device=cpu`; the checkpoint holds host tensors whatever the device."""
    from hammer.cli import app

    runner = CliRunner()
    d = tmp_path / "run"
    res = runner.invoke(app, ["train", "--preset", "cn3", "--run-dir", str(d), "--episodes", "8", "--quiet",
                              *[f"--set={s}" for s in SMALL]])
    assert res.exit_code == 0, res.output
    cfg = json.loads((d / "config.json").read_text())
    (d / "config.json").write_text(json.dumps(dict(cfg, device="cuda:0")))
    if not torch.cuda.is_available():
        res = runner.invoke(app, ["train", "--resume", str(d), "--episodes", "16", "--quiet"])
        assert res.exit_code == 2 and "fix: --set device=cpu" in res.output, res.output
    res = runner.invoke(app, ["train", "--resume", str(d), "--episodes", "16", "--set", "device=cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    assert len(_rows(d)) == 17 and json.loads((d / "config.json").read_text())["device"] == "cpu"
    res = runner.invoke(app, ["train", "--resume", str(d), "--set", "seed=3", "--quiet"])
    assert res.exit_code == 2 and "only --episodes (and --set device=...)" in res.output
