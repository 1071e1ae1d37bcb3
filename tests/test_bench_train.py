"""`hammer bench train` on tiny budgets: every figure present, finite and consistent."""

import math

from hammer.benchmarks.train_bench import run_bench
from typer.testing import CliRunner

from hammer.commands.bench import print_train_table


def test_bench_train_figures(capsys):
    # multiwalker shrunk to one 8 x 25-step update with one epoch (the preset's 1000-step updates
    # take seconds each on a loaded machine)
    r = run_bench("il", cn_episodes=64, mw_updates=1, extrapolate_from=64,
                  mw_overrides={"rollout_steps": 25, "epochs": 1}, mw_warmup=0)
    cn, ref = r["cn3"]["cn"], r["cn3"]["cn-mpe2"]
    assert cn["env"] == "cn" and ref["env"] == "cn-mpe2" and cn["episodes"] == ref["episodes"] == 64
    assert math.isclose(r["cn3"]["ratio"], cn["env_steps_per_s"] / ref["env_steps_per_s"])
    full = r["full"]  # a real `hammer train` process
    assert full["extrapolated"] and full["episodes"] == 64 and full["full_episodes"] == 30_000
    assert math.isclose(full["full_wall_s"], full["startup_s"] + full["loop_s"] * 30_000 / 64)
    assert full["startup_s"] > 0 and full["full_wall_s"] > full["wall_s"]
    mw = r["mw3"]
    assert mw["workers=0"]["env_workers"] == 0 and mw["workers=2"]["env_workers"] == 2
    assert mw["workers=0"]["env_steps"] == mw["workers=0"]["steps_per_update"] == 8 * 25
    assert math.isclose(mw["speedup"], mw["workers=2"]["env_steps_per_s"] / mw["workers=0"]["env_steps_per_s"])
    for x in (cn, ref, full, mw["workers=0"], mw["workers=2"]):
        assert x["env_steps_per_s"] > 0 and math.isfinite(x["env_steps_per_s"]) and x["load_before"] >= 0
    print_train_table(r)
    out = capsys.readouterr().out
    assert "EXTRAPOLATED" in out and "cn-mpe2" in out and "speed-up" in out


def test_bench_train_refuses_empty_budgets():
    from hammer.cli import app

    res = CliRunner().invoke(app, ["bench", "train", "--cn-episodes", "0"])
    assert res.exit_code == 2 and "--cn-episodes" in res.output
