"""The central agent's acting maths (global state, message sampling), without torch.

Two callers run it: `Team.central_messages` (in-process trainer) and the central server
(`central_agent/central_server.py`), both with the numpy forward of `learning.numpy_policy` on the CPU
(the trainer's on a GPU is torch's); the server sits on the critical path of every vector step
and must stay light. The forward pass is passed in as
functions of the numpy state, so the sampling below — and the order and shapes of the stream
draws the randomness contract (`learning.sampling`) pins — exists once for both.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from hammer.envs.base import EnvSpec
from hammer.learning.config import RunConfig
from hammer.learning.numpy_policy import gaussian_logp_of_draw
from hammer.learning.sampling import ActingStreams
from hammer.learning.variant import Wiring

Forward = Callable[[np.ndarray], np.ndarray]


def encode_actions(spec: EnvSpec, actions: np.ndarray, active: np.ndarray) -> np.ndarray:
    """Actions as the central agent sees them: one-hot (discrete) or raw, zero if absent. (K, N, A)."""
    if spec.discrete:
        enc = np.zeros((*actions.shape, spec.action_dim), dtype=np.float32)
        # one flat fancy index (what np.put_along_axis does, without its per-call index building)
        enc.reshape(-1, spec.action_dim)[np.arange(actions.size), actions.reshape(-1).astype(np.int64, copy=False)] = 1.0
    else:
        enc = np.clip(actions, spec.action_low, spec.action_high).astype(np.float32)
    return enc * active[..., None]


def zero_prev_actions(spec: EnvSpec, k: int) -> np.ndarray:
    """The previous actions of a first step: none. (K, N, A)."""
    return np.zeros((k, spec.n_agents, spec.action_dim), dtype=np.float32)


_MIX = np.array([0x9E3779B97F4A7C15, 0xBF58476D1CE4E5B9, 0x94D049BB133111EB, 0xD6E8FEB86659FD93], dtype=np.uint64)


def missing_mask(seed: int, step: int, env_idx: np.ndarray, n_agents: int, prob: float, window: int) -> np.ndarray:
    """(K, N) bool: which robots the central agent sees as missing at vector `step` of env copies
    `env_idx`, in training that simulates absences (RunConfig.missing_prob). A robot is missing for
    whole windows of `window` steps, each with probability `prob`, decided by a hash of (seed,
    window, copy, agent): a pure function of the step, so the trainer, the central server and the
    learner (which rebuilds the states it trains on) agree without sharing a random stream, and no
    stream the randomness contract pins (learning.sampling) is drawn from."""
    # array arithmetic throughout: uint64 wraps around silently (numpy scalars would warn)
    x = (np.asarray(env_idx, np.uint64)[:, None] * _MIX[2] + np.arange(n_agents, dtype=np.uint64)[None, :] * _MIX[3]
         + (np.array([seed, (step - 1) // window], np.uint64) * _MIX[:2]).sum(dtype=np.uint64))
    x = (x ^ (x >> np.uint64(30))) * _MIX[1]  # splitmix64's finaliser
    x = (x ^ (x >> np.uint64(27))) * _MIX[2]
    x ^= x >> np.uint64(31)
    return (x >> np.uint64(11)).astype(np.float64) * 2.0**-53 < prob


@dataclass
class CentralOut:
    """One vector step of central messages, all numpy."""

    sent: np.ndarray  # (K, N, M) float32: what each local agent receives (clipped, after dropout)
    mean: np.ndarray  # (K, N, M) float32: tanh mean of the message policy
    raw: np.ndarray  # (K, N, M) float32: the unclipped Gaussian sample (rl); its logp is trained
    logp: np.ndarray  # (K, N) float32: log-density of raw (rl), else 0
    value: np.ndarray  # (K, N) float32: central critic per message stream (rl), else 0
    keep: np.ndarray  # (K, N) bool: message not dropped


@dataclass(frozen=True)
class CentralActing:
    """The part of a RunConfig the central acting path reads, and the maths it runs."""

    wiring: Wiring
    msg_std: float
    use_prev_actions: bool
    seed: int = 0
    missing_prob: float = 0.0
    missing_window: int = 20
    site_missing_prob: float = 0.0

    @classmethod
    def from_config(cls, cfg: RunConfig) -> CentralActing:
        return cls(cfg.wiring, cfg.msg_std, cfg.use_prev_actions, cfg.seed, cfg.missing_prob, cfg.missing_window,
                   cfg.site_missing_prob)

    def training_site_presence(self, step: int, env_idx: np.ndarray) -> np.ndarray | None:
        """(K,) bool: whether the site feed is there at `step` of a training run that simulates its
        absence (`site_missing_prob`), in windows of `missing_window` steps like a robot's; None when it
        does not. The site is hashed as member N of `missing_mask` (robots are 0..N-1), so the robots'
        absences are the same with or without it."""
        if self.site_missing_prob <= 0:
            return None
        return ~missing_mask(self.seed, step, env_idx, self.n_agents + 1, self.site_missing_prob,
                             self.missing_window)[:, -1]

    def training_state(self, obs: np.ndarray, prev_actions: np.ndarray, step: int, env_idx: np.ndarray,
                       local_obs_dim: int | None) -> np.ndarray:
        """The central agent's state at vector `step` of a training run (copies `env_idx`): the robots
        `missing_prob` takes away, and for an env with central-only columns [local_obs_dim, D) the site
        feed `site_missing_prob` takes away, as zeros (the trainer, `hammer up`'s central server and
        its learner all build it here)."""
        site = self.training_site_presence(step, env_idx) if local_obs_dim is not None else None
        return self.global_state(obs, prev_actions, self.training_presence(step, env_idx),
                                 None if site is None else (local_obs_dim, site))

    def training_presence(self, step: int, env_idx: np.ndarray) -> np.ndarray | None:
        """(K, N) bool: the robots present to the central agent at `step` of a training run that
        simulates absences (`missing_mask`); None when it does not."""
        if self.missing_prob <= 0:
            return None
        return ~missing_mask(self.seed, step, env_idx, self.n_agents, self.missing_prob, self.missing_window)

    @property
    def n_agents(self) -> int:
        return self.wiring.n_agents

    @property
    def msg_dim(self) -> int:
        return self.wiring.msg_dim

    @property
    def has_network(self) -> bool:
        return self.wiring.has_central_network

    @property
    def rl(self) -> bool:
        return self.wiring.central_rl

    def global_state(self, obs: np.ndarray, prev_actions: np.ndarray, present: np.ndarray | None = None,
                     site: tuple[int, np.ndarray] | None = None) -> np.ndarray:
        """s = o_1 ⊕ … ⊕ o_N ⊕ a_1(t-1) ⊕ … ⊕ a_N(t-1) (actions optional). (K, S) float32.

        `present` (K, N) bool: the missing rule, the one a fleet's central agent applies to a silent
        robot and training simulates (`training_presence`): a robot not present is zeros, its
        observation and its previous action. `site` (L, (K,) bool): the site feed's silent rule as
        training simulates it (`training_site_presence`): where it is absent, columns [L, D) of every
        row are zeros (a fleet's central agent writes the zeros into its rows itself)."""
        k = obs.shape[0]
        if site is not None and not site[1].all():
            local, there = site
            obs = obs.copy()
            obs[~there, :, local:] = 0.0
        if present is not None and not present.all():
            obs = np.where(present[..., None], obs, np.float32(0))
            prev_actions = np.where(present[..., None], prev_actions, np.float32(0))
        parts = [obs.reshape(k, -1)]
        if self.use_prev_actions:
            parts.append(prev_actions.reshape(k, -1))
        return np.concatenate(parts, axis=1).astype(np.float32, copy=False)

    def messages(self, state: np.ndarray, streams: ActingStreams, dropout: float,
                 message_mean: Forward | None, values: Forward | None) -> CentralOut:
        """Messages for every agent of every copy from the global state (K, S).

        message_mean: state → (K, N, M) tanh means (variant hammer); values: state → (K, N)
        central critic (rl mode). Neither draws from a stream, so the draws are the same whichever
        network computes them.
        """
        k, n, m = state.shape[0], self.n_agents, self.msg_dim
        zeros_kn = np.zeros((k, n), dtype=np.float32)
        value = zeros_kn
        if self.wiring.random_messages:
            mean = raw = streams.central_uniform_messages(k, n, m)
            sent, logp = raw, zeros_kn
        elif self.has_network:
            if message_mean is None or (self.rl and values is None):
                raise ValueError(f"variant {self.wiring.label} needs the central network's forward")
            mean = message_mean(state)
            if self.rl:
                z = streams.central_normals(k, n, m)
                raw = (mean + self.msg_std * z).astype(np.float32)
                logp = gaussian_logp_of_draw(z, np.log(self.msg_std))
                sent = np.clip(raw, -1.0, 1.0)
                value = values(state)
            else:  # backprop: act on the deterministic message, recomputed with grad at update time
                raw, sent, logp = mean, mean, zeros_kn
        else:
            mean = raw = sent = np.zeros((k, n, 0), dtype=np.float32)
            logp = zeros_kn
        keep = streams.dropout_keep(k, n, dropout) if m else np.ones((k, n), dtype=bool)
        if not keep.all():
            sent = sent * keep[..., None]
        return CentralOut(sent.astype(np.float32, copy=False), mean, raw, logp, value, keep)
