"""The learners' statistics kept with archived runs, and `hammer diagnose` over them, on real
trainer runs with real TensorBoard event files."""

import numpy as np
import pytest
from hammer.experiments.archive import archive_run
from hammer.experiments.diagnose import DIAG_STATS, diagnose
from hammer.experiments.runs import best_rolling, load_run, rolling_mean
from hammer.experiments.train_stats import TRAIN_STATS_NPZ, load_train_stats, read_tensorboard
from hammer.learning.config import merge_config
from hammer.learning.rundir import RunDir
from hammer.learning.trainer import train
from typer.testing import CliRunner

SETS = ["num_envs=8", "rollout_steps=25", "epochs=2", "minibatches=2", "variant=hammer", "central_mode=rl",
        "checkpoint_every=3", "seed=2"]


def _train(root, name, episodes, resume=False, tensorboard=True):
    if resume:
        rd, cfg = RunDir.open(root / name)
        cfg = cfg.model_copy(update={"episodes": episodes})
    else:
        cfg = merge_config("cn3", overrides=SETS + [f"episodes={episodes}"])
        rd = RunDir.create(root / name, cfg)
    return train(cfg, rd, resume=resume, tensorboard=tensorboard)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    _train(root, "full", 160)
    # interrupted at 80 episodes and resumed from an older checkpoint: its TensorBoard log holds
    # updates past that checkpoint, which the resumed run logs again; the purge must drop exactly
    # those (it once also dropped the update logged at the checkpoint itself)
    _train(root, "cut", 80)
    max((root / "cut" / "checkpoints").glob("ckpt_*.json")).unlink()
    _train(root, "cut", 160, resume=True)
    _train(root, "notb", 40, tensorboard=False)
    archive = root / "archive"
    for name in ("full", "cut", "notb"):
        archive_run(root / name, archive)
    return root, archive


def test_archived_statistics_are_the_tensorboard_ones_and_a_resumed_run_matches(runs):
    root, archive = runs
    tb = read_tensorboard(root / "full")
    assert {t for t, _ in DIAG_STATS} <= set(tb) and "train/central/approx_kl" in tb
    full = load_train_stats(archive / "full")
    assert set(full) == set(tb)
    episodes = np.loadtxt(root / "full" / "metrics.csv", delimiter=",", skiprows=1, usecols=(0, 1))
    for tag, (steps, values) in tb.items():
        ep, v = full[tag]
        np.testing.assert_array_equal(v, values.astype(np.float64))
        # x axis: episodes finished by the update's env-step count, from metrics.csv
        np.testing.assert_array_equal(ep, [int((episodes[:, 1] <= s).sum()) for s in steps])
    assert np.all(np.diff(full["train/local/entropy"][0]) > 0)  # one point per update, 8 episodes each
    cut = load_train_stats(archive / "cut")
    assert set(cut) == set(full)
    for tag in full:
        np.testing.assert_array_equal(cut[tag][0], full[tag][0])
        np.testing.assert_array_equal(cut[tag][1], full[tag][1])
    # the raw event files of the resumed run really do hold steps twice
    assert len(list((root / "cut" / "tb").glob("events.out.tfevents.*"))) == 2


def test_a_run_without_tensorboard_is_archived_without_statistics(runs):
    root, archive = runs
    assert (archive / "notb" / "summary.json").is_file()
    assert not (archive / "notb" / TRAIN_STATS_NPZ).exists()
    assert load_train_stats(archive / "notb") == {} == load_train_stats(root / "notb")


def test_diagnosis_splits_the_statistics_at_the_best_episode(runs):
    _, archive = runs
    run = load_run(archive / "full")
    d = diagnose(run, window=20, last=30)
    rm = rolling_mean(run.paper_metric, 20)
    assert d.best == pytest.approx(rm[19:].max()) and d.best_episode == 20 + int(np.argmax(rm[19:]))
    assert (d.best, d.best_episode) == best_rolling(run.paper_metric, 20)
    assert d.final == pytest.approx(run.paper_metric[-30:].mean())
    ep, v = load_train_stats(archive / "full")["train/local/approx_kl"]
    i = int((ep <= d.best_episode).sum())
    at_best, at_end, before, after = d.stats["train/local/approx_kl"]
    assert at_best == v[i - 1] and at_end == v[-1]
    assert before == pytest.approx(np.median(v[:i]))
    assert (after == pytest.approx(np.median(v[i:]))) if i < len(v) else np.isnan(after)
    assert diagnose(load_run(archive / "notb"), window=20).stats == {}


def test_cli_diagnose(runs, tmp_path):
    from hammer.cli import app

    _, archive = runs
    res = CliRunner().invoke(app, ["diagnose", str(archive), "--window", "20", "--out", str(tmp_path / "d"),
                                   "--table", str(tmp_path / "d.md")])
    assert res.exit_code == 0, res.output
    md = (tmp_path / "d.md").read_text()
    rows = {line.split("|")[1].strip(): line for line in md.splitlines() if line.startswith("| ") and "---" not in line}
    assert set(rows) == {"run", "full", "cut", "notb"}
    assert rows["full"] == rows["cut"].replace("| cut |", "| full |")  # resumed exactly
    assert rows["notb"].rstrip().endswith("| – | – | – |")
    assert all((tmp_path / f"d{ext}").stat().st_size > 1000 for ext in (".png", ".svg"))
    res = CliRunner().invoke(app, ["diagnose", str(tmp_path / "nope")])
    assert res.exit_code == 2 and "does not exist" in res.output
