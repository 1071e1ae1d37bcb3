"""`hammer bench kernels` on a tiny budget: the floor is made of the run's own layers, is below
the real loop, and the command refuses an unknown variant in one line."""

import math

from hammer.benchmarks.kernels import measure
from typer.testing import CliRunner


def test_kernels_floor_is_the_layers_and_below_the_real_update():
    r = measure("hammer", compile_=False, updates=1, repeats=10, central_mode="rl")
    parts = r["parts_ms"]
    # every network an update trains is in the floor: the local actor and critic, the central net
    assert {p.split(".")[1] + "." + p.split(".")[2] for p in parts} >= {"local.actor", "local.critic"}
    assert any(p.startswith("update.central.") for p in parts)
    assert math.isclose(sum(v for k, v in parts.items() if k.startswith("update.")), r["update_floor_ms"], rel_tol=0.01)
    # the floor leaves out the optimiser, the losses and Python: the real update costs more
    assert 0 < r["update_floor_ms"] < r["update_ms"]
    assert 0 < r["env_ms"] < r["collect_ms"]
    assert r["floor_env_steps_per_s"] > r["env_steps_per_s"] > 0
    assert "8 epochs x 4 minibatches of 200 samples" in r["schedule"]


def test_bench_kernels_refuses_an_unknown_variant():
    from hammer.cli import app

    res = CliRunner().invoke(app, ["bench", "kernels", "--variants", "mappo"])
    assert res.exit_code != 0 and "--variants" in res.output and "mappo" in res.output
