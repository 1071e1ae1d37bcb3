"""The randomness contract for acting (numpy only).

Every random draw made while acting comes from a named stream
`np.random.default_rng([seed, STREAM_ID, index])`, and every stream draws the same amount every
vector step (the full K, even for absent agents), so a stream's position depends only on the step
count. The in-process trainer and the distributed runtime (one process per agent) therefore draw
identical numbers and, given identical logits, take identical actions and send identical messages.
A categorical action is `categorical.draw(logits, u)` on every machine (`categorical_draw`: exact
where an exp's last bit could matter), so the plain-Python lite agent draws what numpy draws.

Per vector step with K copies, N agents, A actions, M message length:
  local agent i     u = rng_local[i].random(K)            categorical by inverse CDF (`categorical_draw`)
                    z = rng_local[i].standard_normal((K, A))  Gaussian: a = mean + std * z
  central (rl)      z = rng_central.standard_normal((K, N, M)); u = clip(mean + msg_std z, -1, 1)
  central (random)  u = rng_central.uniform(-1, 1, (K, N, M))
  dropout (p > 0)   keep = rng_dropout.random((K, N)) >= p
"""

from __future__ import annotations

from typing import Any

import numpy as np
from hammer.learning import categorical
from hammer.learning.numpy_policy import softmax

LOCAL_STREAM = 1
CENTRAL_STREAM = 2
DROPOUT_STREAM = 3
ENV_RESEED_STREAM = 4
MINIBATCH_STREAM = 5


def stream(seed: int, stream_id: int, index: int = 0) -> np.random.Generator:
    return np.random.default_rng([seed, stream_id, index])


def categorical_inverse_cdf(probs: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Sample index a with cdf[a-1] <= u < cdf[a]; probs (..., A), u (...) in [0, 1)."""
    cdf = np.cumsum(probs, axis=-1)
    idx = (cdf <= u[..., None]).sum(axis=-1)
    return np.minimum(idx, probs.shape[-1] - 1).astype(np.int64)


def categorical_draw(logits: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(action, probs): the categorical draw of the contract for logits (..., A) and uniforms (...),
    and the float64 softmax it was drawn from (what a log-probability is taken of).

    The action is `categorical.draw` of each row, the same on every machine: numpy's softmax (its
    exp is the CPU's) decides every row whose uniform lies at least `categorical.MARGIN` from its
    CDF values, and a row closer than that is drawn by the exact softmax in plain Python (rare:
    about 1e-8 of the draws). The returned probabilities are numpy's."""
    probs = softmax(logits)
    # cdf - u for all CDF values but the last (the action counts those at or below u; the last
    # would only count past A - 1, which the index is clipped to anyway)
    gap = np.cumsum(probs[..., :-1], axis=-1)
    gap -= u[..., None]
    idx = (gap <= 0).sum(axis=-1).astype(np.int64, copy=False)
    near = np.abs(gap, out=gap)
    if near.size and not near.min() >= categorical.MARGIN:  # `not >=`: a nan row is drawn exactly too
        rows = ~(near >= categorical.MARGIN).all(axis=-1)
        idx[rows] = [categorical.draw(row, x) for row, x in zip(np.asarray(logits)[rows].tolist(), u[rows].tolist())]
    return idx, probs


def env_reset_seed(seed: int, update: int) -> int:
    """Seed for `VecEnv.reset` at a checkpoint point (copy k gets this + k)."""
    return int(np.random.SeedSequence([seed, ENV_RESEED_STREAM, update]).generate_state(1)[0] % (2**31 - 2**20))


class ActingStreams:
    """All acting streams of one run: N local, one central, one dropout."""

    def __init__(self, seed: int, n_agents: int) -> None:
        self.local = [stream(seed, LOCAL_STREAM, i) for i in range(n_agents)]
        self.central = stream(seed, CENTRAL_STREAM, 0)
        self.dropout = stream(seed, DROPOUT_STREAM, 0)

    def local_uniforms(self, k: int) -> np.ndarray:
        """(K, N): one uniform per copy from each agent's own stream."""
        return np.stack([rng.random(k) for rng in self.local], axis=1)

    def local_normals(self, k: int, a: int) -> np.ndarray:
        """(K, N, A)."""
        return np.stack([rng.standard_normal((k, a)) for rng in self.local], axis=1)

    def central_normals(self, k: int, n: int, m: int) -> np.ndarray:
        return self.central.standard_normal((k, n, m))

    def central_uniform_messages(self, k: int, n: int, m: int) -> np.ndarray:
        return self.central.uniform(-1.0, 1.0, (k, n, m)).astype(np.float32)

    def dropout_keep(self, k: int, n: int, p: float) -> np.ndarray:
        """(K, N) bool; draws nothing when p == 0 so dropout-free runs need no dropout stream."""
        if p <= 0:
            return np.ones((k, n), dtype=bool)
        return self.dropout.random((k, n)) >= p

    def state(self) -> dict[str, Any]:
        """JSON-serialisable generator states (plain ints and strings, never pickle)."""
        return {
            "local": [rng.bit_generator.state for rng in self.local],
            "central": self.central.bit_generator.state,
            "dropout": self.dropout.bit_generator.state,
        }

    def set_state(self, state: dict[str, Any]) -> None:
        if len(state["local"]) != len(self.local):
            raise ValueError(f"stream state has {len(state['local'])} local agents, expected {len(self.local)}")
        for rng, s in zip(self.local, state["local"]):
            rng.bit_generator.state = s
        self.central.bit_generator.state = state["central"]
        self.dropout.bit_generator.state = state["dropout"]
