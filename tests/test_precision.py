"""`precision`: fp32 (default) or bf16, the PPO update's forward passes under bfloat16 autocast.

bf16 is refused in one line on hardware without native bfloat16 matmuls; where this host has none,
the bf16 runs here lift the refusal with the documented `HAMMER_ALLOW_EMULATED_BF16=1` (the same
maths, emulated by torch, slower)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from hammer.learning.config import ConfigError, config_changes, merge_config
from hammer.learning.ppo_update import TeamLearner
from hammer.learning.precision import EMULATED_ENV, bf16_unsupported
from hammer.learning.run_env import make_env
from hammer.learning.rundir import RunDir
from hammer.learning.trainer import Trainer, train
from typer.testing import CliRunner

from tests.runtime_helpers import COMPILE_NETS

SMALL = ["num_envs=4", "rollout_steps=25", "epochs=2", "minibatches=2", "checkpoint_every=1"]
NO_NATIVE_BF16 = bf16_unsupported(torch.device("cpu"))


def _cfg(*extra: str, episodes: int = 12):
    return merge_config("cn3", overrides=[*SMALL, "variant=hammer", "central_mode=rl", f"episodes={episodes}", *extra])


def _rows(path: Path) -> list[list[str]]:
    with open(path / "metrics.csv", newline="") as f:
        return [r[:5] for r in csv.reader(f)]  # without the wall time


@pytest.fixture
def bf16_here(monkeypatch: pytest.MonkeyPatch) -> None:
    """bf16 runs on this host: natively, or emulated where it has no native bfloat16."""
    if NO_NATIVE_BF16:
        monkeypatch.setenv(EMULATED_ENV, "1")


def test_the_field_defaults_to_fp32_and_names_itself_when_wrong():
    assert merge_config("cn3").precision == "fp32"
    assert merge_config("cn3", overrides=["precision=bf16"]).precision == "bf16"
    for bad in ("fp16", "bfloat16", "16"):
        with pytest.raises(ConfigError) as e:
            merge_config("cn3", overrides=[f"precision={bad}"])
        msg = str(e.value)
        assert msg.startswith("config field 'precision'") and "fix: use fp32 or bf16" in msg and "\n" not in msg


def test_a_float32_config_dumps_as_before_and_bf16_is_recorded():
    """fp32 leaves the field out of every dump (config.json, checkpoints, snapshots: unchanged
    bytes); bf16 writes it, and a config without it reads as fp32 wherever configs are compared."""
    from hammer.experiments.runs import setting_changes

    fp32, bf16 = merge_config("cn3").model_dump(mode="json"), merge_config("cn3", overrides=["precision=bf16"]).model_dump(mode="json")
    assert "precision" not in fp32 and bf16["precision"] == "bf16"
    assert {k: v for k, v in bf16.items() if k != "precision"} == fp32
    assert config_changes(bf16, fp32) == {"precision": "bf16"} and config_changes(fp32, bf16) == {"precision": "fp32"}
    assert setting_changes(bf16) == ['precision="bf16"'] and setting_changes(fp32) == []
    assert merge_config(base=bf16).precision == "bf16" and merge_config(base=fp32).precision == "fp32"


@pytest.mark.skipif(not NO_NATIVE_BF16, reason="this host has native bfloat16: nothing to refuse")
def test_bf16_is_refused_without_native_bfloat16_naming_the_field_and_the_fix(tmp_path, monkeypatch):
    monkeypatch.delenv(EMULATED_ENV, raising=False)
    with pytest.raises(ConfigError) as err:
        Trainer(_cfg("precision=bf16"), RunDir(tmp_path / "never"))
    msg = str(err.value)
    assert msg.startswith("config field 'precision': precision=bf16 needs native bfloat16 matmuls")
    assert "avx512_bf16" in msg and msg.endswith("fix: --set precision=fp32 (or run on an AVX512_BF16/AMX CPU or a bf16 GPU)")
    assert "\n" not in msg and not (tmp_path / "never").exists()
    from hammer.cli import app

    for seeds in ([], ["--seeds", "0-1"]):
        res = CliRunner().invoke(app, ["train", "--preset", "cn3", "--set", "precision=bf16", "--episodes", "8",
                                       "--out", str(tmp_path / "cli"), "--quiet", *seeds])
        assert res.exit_code == 2 and "fix: --set precision=fp32" in res.output, res.output
    assert not (tmp_path / "cli").exists()  # refused before any env or file


def test_the_float32_update_is_the_plain_one_and_bf16_runs_the_forward_in_bfloat16(bf16_here):
    """fp32: `losses` is `_losses` bit for bit (no autocast, the networks' float32 outputs are the
    tensors they were). bf16: the same batch gives float32 losses that differ from fp32's by
    bfloat16's rounding, not more."""
    out = {}
    for precision in ("fp32", "bf16"):
        cfg = _cfg(f"precision={precision}")
        env = make_env(cfg)
        learner = TeamLearner(cfg, env.spec)
        rng = np.random.default_rng(0)
        for name, arr in learner.buf.arrays.items():
            arr[...] = rng.random(arr.shape) if arr.dtype.kind == "f" else name == "active"  # every agent present
        obs, _ = env.reset(0)
        b, masks = learner.batch(obs, learner.team.zero_prev_actions(cfg.num_envs))
        local, central, _ = learner.losses(b, masks)
        out[precision] = (local, central)
        if precision == "fp32":
            plain = learner._losses(b, masks)
            assert torch.equal(local, plain[0]) and torch.equal(central, plain[1])
        assert local.dtype == central.dtype == torch.float32
        env.close()
    (l32, c32), (l16, c16) = out["fp32"], out["bf16"]
    assert not torch.equal(l32, l16) and not torch.equal(c32, c16)
    assert l16.item() == pytest.approx(l32.item(), rel=5e-2, abs=5e-3)
    assert c16.item() == pytest.approx(c32.item(), rel=5e-2, abs=5e-3)


def test_a_bf16_run_trains_records_its_precision_and_resumes_bit_exactly(tmp_path, bf16_here):
    cfg = _cfg("precision=bf16", episodes=24)
    summary = train(cfg, RunDir.create(tmp_path / "bf16", cfg), tensorboard=False)
    assert summary["episodes"] == 24 and summary["updates"] >= 5
    assert json.loads((tmp_path / "bf16" / "config.json").read_text())["precision"] == "bf16"
    stem = RunDir(tmp_path / "bf16").latest_checkpoint()
    tensors, meta = RunDir.load_checkpoint(stem)
    assert meta["config"]["precision"] == "bf16"
    assert all(t.dtype == torch.float32 for k, t in tensors.items() if k.startswith(("local/", "opt_local")) and t.is_floating_point())
    # the float32 run of the same seed learns other weights (the update's rounding differs)
    fp32 = _cfg(episodes=24)
    train(fp32, RunDir.create(tmp_path / "fp32", fp32), tensorboard=False)
    assert "precision" not in json.loads((tmp_path / "fp32" / "config.json").read_text())
    t32, _ = RunDir.load_checkpoint(RunDir(tmp_path / "fp32").latest_checkpoint())
    assert any(not torch.equal(t32[k], tensors[k]) for k in tensors if k.startswith("local/"))
    # cut at 12 episodes and resumed: bit for bit the uninterrupted bf16 run
    cut = _cfg("precision=bf16", episodes=12)
    train(cut, RunDir.create(tmp_path / "cut", cut), tensorboard=False)
    rd, cfg2 = RunDir.open(tmp_path / "cut")
    assert cfg2.precision == "bf16"
    train(cfg2.model_copy(update={"episodes": 24}), rd, resume=True, tensorboard=False)
    assert _rows(tmp_path / "cut") == _rows(tmp_path / "bf16")


def test_a_bf16_seed_batch_trains(tmp_path, bf16_here):
    """vmap over the seeds with autocast inside the loss: trains and records the field per seed."""
    from hammer.learning.seed_batch import train_seeds

    cfgs = [_cfg("precision=bf16", f"seed={s}") for s in (0, 1)]
    dirs = [RunDir.create(tmp_path / str(c.seed), c) for c in cfgs]
    assert [s["episodes"] for s in train_seeds(cfgs, dirs, tensorboard=False)] == [12, 12]
    assert [json.loads((tmp_path / str(s) / "config.json").read_text())["precision"] for s in (0, 1)] == ["bf16"] * 2


@pytest.mark.slow
@pytest.mark.timeout(1800)  # one compile; on a loaded 2-core machine one took over 5 min
def test_the_compiled_update_runs_under_bf16(tmp_path, bf16_here):
    """compile=true (one graph per epoch, as seed batches and grids run) traces the autocast region
    into its graph: the run trains, and its weights are bfloat16's distance from the eager float32
    run's (compiling alone moves them by rounding, ~1e-7; bfloat16 by ~1e-4)."""
    rows = {}
    for name, extra in (("fp32", ()), ("bf16", ("precision=bf16", "compile=true", "compile_scope=epoch"))):
        cfg = _cfg(*COMPILE_NETS, *extra)
        train(cfg, RunDir.create(tmp_path / name, cfg), tensorboard=False)
        rows[name] = RunDir.load_checkpoint(RunDir(tmp_path / name).latest_checkpoint())[0]
    gap = max((rows["fp32"][k] - rows["bf16"][k]).abs().max().item() for k in rows["fp32"] if k.startswith("local/"))
    assert gap > 1e-5, gap
