"""`hammer bench scale` pieces that must hold whatever the machine's speed: the rollout chunk's cap
at large N, the three-way split of a step, the table and the plot from a result."""

from __future__ import annotations

import numpy as np
import pytest
from hammer.benchmarks.scale import markdown, plot, pooled_size, scale_config, shares
from hammer.protocol.codec import decode, encode
from hammer.protocol.dims import Dims
from hammer.protocol.errors import SizeError
from hammer.protocol.fields import MiB
from hammer.protocol.rollout_layout import RolloutLayout
from hammer.protocol.schemas import ExperienceChunk


def test_the_rollout_chunk_cap_grows_with_the_run_and_still_refuses_more():
    """cn3's chunk fits the default 64 MiB cap; a layout whose chunk is larger gets its own size +
    1 MiB, derived the same way by the env host (sender) and the learner (receiver)."""
    small = RolloutLayout(t=25, k=32, n=3, obs_dim=18, action_dim=5, msg_dim=4, discrete=True)
    assert ExperienceChunk.cap_for(small) == ExperienceChunk.MAX_BYTES
    big = RolloutLayout(t=2, k=4, n=50, obs_dim=300, action_dim=5, msg_dim=8, discrete=True)
    assert big.chunk_nbytes() == sum(a.nbytes for a in _chunk(big).values())
    cap = big.chunk_nbytes() + 1024  # a cap just above this chunk: what cap_for does for a chunk over 64 MiB
    data = encode(ExperienceChunk(step=3, env_idx=np.arange(4), role="team", policy_version=0, arrays=_chunk(big)),
                  stamp={"sender": "env"}, max_bytes=cap + MiB)
    assert decode(data, ExperienceChunk, Dims.from_layout(big), max_bytes=cap + MiB).arrays["obs"].shape[2] == 50
    with pytest.raises(SizeError):
        decode(data, ExperienceChunk, max_bytes=len(data) - 1)


def _chunk(layout: RolloutLayout) -> dict[str, np.ndarray]:
    arrays = layout.chunk_steps()
    from hammer.protocol.rollout_layout import CHUNK

    return {**arrays, **layout.allocate(tuple(s for s in CHUNK if not s.shape.startswith("T")))}


def test_the_scale_configs_and_pool_sizes():
    assert scale_config(3, 10).msg_dim == 4 and scale_config(20, 10).msg_dim == 8
    assert scale_config(50, 10).n_agents == 50 and scale_config(50, 10).num_envs == 32
    assert all(pooled_size(n) > 1 for n in (3, 5, 20, 50))  # every N gets a pooled figure


def _row(n: int, p50: float, floor_typed: float, floor_raw: float) -> dict:
    up = {"env_steps_per_s": 100.0 * n, "p50_ms": p50, "p99_ms": 2 * p50, "msgs_per_step": 2.0 * n + 2,
          "bytes_per_step": 1000.0 * n, "processes": n + 3,
          "cpu_ms_per_step": {"env": 1.0, "central": 1.0, "learner": 2.0, "local": 0.5 * n},
          "rss_mib": {"env": 100.0, "central": 90.0, "learner": 400.0, "local": 80.0}}
    floor = {f"{t}_{m}_p{q}_ms": v for t in ("split", "pooled") for m, v in (("typed", floor_typed),
                                                                             ("raw", floor_raw)) for q in (50, 99)}
    row = {"n_agents": n, "pool_size": n, "train": {"env_steps_per_s": 200.0 * n, "cpu_ms_per_step": {"train": 3.0},
                                                    "rss_mib": {"train": 300.0}},
           "up": up, "up_pools": dict(up), "floor": floor}
    row["shares_up"] = shares(up, floor, "split")
    row["shares_pools"] = shares(up, floor, "pooled")
    return row


def test_the_step_split_the_table_and_the_plot(tmp_path):
    s = shares({"p50_ms": 5.0}, {"split_raw_p50_ms": 1.0, "split_typed_p50_ms": 2.5}, "split")
    assert s == {"zenoh_sched_ms": 1.0, "codec_validation_ms": 1.5, "work_ms": 2.5}
    result = {"meta": {"date": "2026-12-03", "cpu_count": 2}, "rows": [_row(3, 4.0, 2.0, 1.0), _row(20, 12.0, 8.0, 3.0)]}
    table = markdown(result)
    assert "| 3 | 600 | 300 (0.50) |" in table and "| 20 | 4,000 | 2,000 (0.50) |" in table
    assert "| 20 | up | 3.00 | 5.00 | 4.00 |" in table  # raw floor, typed - raw, p50 - typed
    plot(result, tmp_path / "scale.png")
    assert (tmp_path / "scale.png").stat().st_size > 10_000
