"""Rollout arrays: the learner's buffer, and the one per-step write every runner does into them.

The arrays and their shapes are the learner's part of the rollout layout
(`protocol.rollout_layout.BUFFER`), which the env host's chunk and the central agent's records
are declared beside. The in-process trainer and the env host both record a vector step through
`RolloutWriter`, so "`hammer up` reproduces `hammer train`" holds by construction: the same
arrays, the same reset marks, the same previous-action encoding with zeros after a reset.
Torch-free: the env host uses it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from hammer.envs.base import EnvSpec, VecStep
from hammer.learning.central_acting import encode_actions
from hammer.protocol.rollout_layout import BUFFER, allocate


class RolloutBuffer:
    """Everything one update needs, time-major; `flat(name)` views it as (T*K, N, ...) rows."""

    obs: np.ndarray
    state: np.ndarray
    msg: np.ndarray  # what the local agents received
    msg_raw: np.ndarray  # central Gaussian sample (rl)
    keep: np.ndarray  # message not dropped
    actions: np.ndarray
    logp: np.ndarray
    values: np.ndarray
    c_logp: np.ndarray
    c_values: np.ndarray
    rewards: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    active: np.ndarray
    reset: np.ndarray  # the copy was reset after this step
    final_values: np.ndarray  # V(final_obs) where reset
    c_final_values: np.ndarray

    def __init__(self, t: int, k: int, n: int, obs_dim: int, state_dim: int, msg_dim: int,
                 action_shape: tuple[int, ...], discrete: bool) -> None:
        self.t, self.k, self.n = t, k, n
        sizes = {"T": t, "K": k, "N": n, "D": obs_dim, "S": state_dim, "M": msg_dim}
        self.arrays = allocate(BUFFER, sizes, action_shape, discrete)
        for name, a in self.arrays.items():
            setattr(self, name, a)

    def flat(self, name: str) -> np.ndarray:
        a = getattr(self, name)
        return a.reshape(self.t * self.k, *a.shape[2:])


@dataclass
class NextPrev:
    """The previous actions of the next step, and the copies whose episode this step ended."""

    prev: np.ndarray  # (K, N, A) this step's actions as the central agent sees them; 0 where reset
    reset_idx: np.ndarray  # copies reset after this step
    final_prev: np.ndarray  # (len(reset_idx), N, A) their actions of this step (before the zeroing)


def next_prev_actions(spec: EnvSpec, actions: np.ndarray, st: VecStep) -> NextPrev:
    """A copy that was reset starts its next episode with no previous actions."""
    prev = encode_actions(spec, actions, st.active)
    if not st.done.any():
        return NextPrev(prev, _NO_RESET, prev[_NO_RESET])
    idx = np.flatnonzero(st.done)
    final_prev = prev[idx]
    prev[idx] = 0.0
    return NextPrev(prev, idx, final_prev)


_NO_RESET = np.zeros(0, dtype=np.int64)


class RolloutWriter:
    """Records one vector step at time index t into rollout arrays (name -> (T, K, ...)).

    Both runners write obs, msg, actions, rewards, terminated, truncated, active and reset. The
    env host's chunk also carries what the learner needs to recompute the rest (prev, final_obs,
    final_prev, written when those arrays are present); the trainer computes global states and
    bootstrap values itself, from the returned `NextPrev`.
    """

    def __init__(self, arrays: dict[str, np.ndarray], spec: EnvSpec) -> None:
        self.arrays, self.spec = arrays, spec
        self.carries_final = "final_obs" in arrays

    def begin(self) -> None:
        """A new rollout: no copy reset yet."""
        self.arrays["reset"][:] = False

    def write(self, t: int, obs: np.ndarray, prev: np.ndarray, msg: np.ndarray, actions: np.ndarray,
              st: VecStep) -> NextPrev:
        a = self.arrays
        a["obs"][t], a["msg"][t], a["actions"][t] = obs, msg, actions
        a["rewards"][t], a["terminated"][t], a["truncated"][t] = st.reward, st.terminated, st.truncated
        a["active"][t] = st.active
        nxt = next_prev_actions(self.spec, actions, st)
        if nxt.reset_idx.size:
            a["reset"][t, nxt.reset_idx] = True
        if self.carries_final:
            a["prev"][t] = prev
            if nxt.reset_idx.size:
                a["final_obs"][t, nxt.reset_idx] = st.final_obs[nxt.reset_idx]
                a["final_prev"][t, nxt.reset_idx] = nxt.final_prev
        return nxt
