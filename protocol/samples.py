"""One valid message of every protocol type: for tests here and in other packages, and the bench."""

from __future__ import annotations

import numpy as np
from hammer.protocol.schemas import (
    Action,
    CentralMsg,
    Control,
    ExperienceChunk,
    GlobalState,
    Heartbeat,
    LocalObs,
    Message,
    SiteState,
    Uplink,
    Weights,
    WeightsAnnounce,
    WeightsChunk,
)

K, N, D, M, A = 4, 3, 18, 4, 5


def sample_messages(seed: int = 0) -> list[Message]:
    rng = np.random.default_rng(seed)
    idx = np.arange(K, dtype=np.int64)
    h = {"step": 7, "env_idx": idx, "sender": "tester"}

    def f32(*shape: int) -> np.ndarray:
        return rng.standard_normal(shape).astype(np.float32)

    return [
        LocalObs(**h, agent=1, obs=f32(K, D), active=np.array([True, False, True, True])),
        GlobalState(**h, obs=f32(K, N, D), prev_actions=np.eye(A, dtype=np.float32)[rng.integers(0, A, (K, N))],
                    active=np.ones((K, N), bool)),
        CentralMsg(**h, agent=2, msg=np.tanh(f32(K, M)), policy_version=3),
        Action(**h, agent=0, action=rng.integers(0, A, K), policy_version=3,
               fallback=np.array([False, True, False, False])),
        Action(**h, agent=0, action=np.clip(f32(K, 4), -1, 1)),
        ExperienceChunk(**h, role="local", policy_version=2,
                        arrays={"obs": f32(8, K, D), "action": rng.integers(0, A, (8, K)),
                                "done": np.zeros((8, K), bool), "img": np.zeros((2, 3), np.uint8),
                                "v64": rng.standard_normal(3), "i32": np.arange(3, dtype=np.int32)},
                        meta={"lr": 3e-4, "note": "x", "n": 3, "flag": True, "none": None}),
        Weights.from_blob("central", 4, bytes(rng.integers(0, 256, 1000, dtype=np.uint8)), **h),
        WeightsAnnounce.of("local", 5, bytes(rng.integers(0, 256, 3000, dtype=np.uint8)), 1024, **h),
        WeightsChunk(**h, role="local", version=5, index=2, data=bytes(rng.integers(0, 256, 952, dtype=np.uint8))),
        Uplink(**h, agent=1, obs=f32(K, D), action=rng.integers(0, A, K)),
        Uplink(**h, agent=2, obs=f32(K, D)),
        SiteState(**h, cols=f32(K, 2 * D)),
        LocalObs(**{**h, "env_idx": np.array([5, 2], np.int64)}, agent=0, obs=f32(2, D), policy_version=1),
        Action(**h, agent=2, action=np.array([0, 300, 2, 1]), msg=np.tanh(f32(K, M)), policy_version=1),
        Control(**h, command="stop", target="learner", args={"path": "runs/a", "every": 10}),
        Heartbeat(**h, role="env", pid=42, status="running", counters={"steps": 100, "busy_s": 950.5},
                  gauges={"policy_version": -1, "paper_metric_100": -15.2}),
    ]


def assert_same(a: Message, b: Message) -> None:
    """Field-by-field equality, comparing arrays by dtype, shape and values."""
    assert type(a) is type(b)
    for name in type(a).__struct_fields__:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y), name
        elif isinstance(x, dict):
            assert x.keys() == y.keys(), name
            for k in x:
                if isinstance(x[k], np.ndarray):
                    assert x[k].dtype == y[k].dtype and np.array_equal(x[k], y[k]), f"{name}.{k}"
                else:
                    assert x[k] == y[k], f"{name}.{k}"
        else:
            assert x == y, name
