"""What a local agent sees, cut from the full observation the environment returns.

HAMMER's premise is that the central agent knows what the local agents do not. To grade that, the
environment keeps returning the FULL per-agent observations: they build the central agent's global
state (`GlobalState`, `Team.global_state`) and are what the rollout records. A `LocalView` then
masks the part a local agent may not see, and it is applied at exactly two places, both numpy:

* `Team` (trainer and learner): before every local-policy forward and on the minibatch
  observations of the PPO update, so the trainer and the distributed learner compute on the same
  masked input from the same recorded full observation;
* the env host: on each `LocalObs` it publishes, so a local agent process (numpy only, no torch)
  receives only what it may see, while the `GlobalState` it publishes stays full.

Masking is a pure function of the full observation, so both places give the same bits.

Envs with central-only columns (`EnvSpec.local_obs_dim`, the central state hook, e.g. rware): the
columns from `local_obs_dim` on carry what only the central agent may know (the whole warehouse);
`CentralColumnsView` zeroes them. The width stays the same, for the reason below.

cn (`envs.spread`) with `env_kwargs.obs_radius=r`: a landmark or another agent is visible to agent
i only if its distance from i is below r; the slots of a hidden one (its relative position, 2
values) are set to 0. Own velocity and position are always visible, so r=0 leaves nothing but
those, and a radius larger than any distance hides nothing (the result equals the full view). A
hidden slot reads like an entity at the agent's own position; the policy cannot tell the two apart
except through the other slots, a deliberate simplification that keeps every observation the same
width (so networks, schemas and exported policies are unchanged). Off (`obs_radius` unset) is the
identity and returns its argument itself: default runs are bit-for-bit what they were.

The fully centralised variant feeds one policy every agent's observation; it is the bound on what
full information gives, so it always sees the full observations.
"""

from __future__ import annotations

from typing import Any

import numpy as np


class LocalView:
    """Identity: a local agent sees its whole observation (every env without a local-view option)."""

    active = False

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return obs

    def describe(self) -> str:
        return "full observation"


class SpreadRadiusView(LocalView):
    """cn with observe_others: mask landmarks and other agents at distance >= radius.

    Observation layout per agent (envs.spread): [v (2), p (2), landmark_l - p for l < N (2N),
    p_j - p for the N-1 others (2(N-1)), communication zeros (2(N-1))].
    """

    active = True

    def __init__(self, n_agents: int, radius: float) -> None:
        self.n, self.radius = n_agents, float(radius)
        # Relative-position pairs: N landmarks then N-1 other agents, starting at column 4.
        self.n_pairs = n_agents + (n_agents - 1)
        self.r2 = self.radius * self.radius

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """(..., D) float32 full observations -> (..., D) masked copy."""
        out = np.array(obs, dtype=np.float32, copy=True)
        rel = out[..., 4:4 + 2 * self.n_pairs].reshape(*out.shape[:-1], self.n_pairs, 2)
        d2 = np.square(rel[..., 0], dtype=np.float64) + np.square(rel[..., 1], dtype=np.float64)
        rel[d2 >= self.r2] = 0.0  # rel is a view into out
        return out

    def describe(self) -> str:
        return f"landmarks and agents within {self.radius:g}"


class CentralColumnsView(LocalView):
    """An env with central-only columns (`EnvSpec.local_obs_dim`, e.g. rware's whole warehouse):
    zero columns [local_obs_dim, D) so a local agent sees only its own part of the row."""

    active = True

    def __init__(self, local_obs_dim: int) -> None:
        self.local_obs_dim = int(local_obs_dim)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        out = np.array(obs, dtype=np.float32, copy=True)
        out[..., self.local_obs_dim:] = 0.0
        return out

    def describe(self) -> str:
        return f"own view (first {self.local_obs_dim} values; the rest is for the central agent)"


def local_view_for(env: str, n_agents: int, env_kwargs: dict[str, Any], joint_obs: bool = False,
                   local_obs_dim: int | None = None) -> LocalView:
    """The local view a run asks for: the env's central-only columns (`local_obs_dim`, from its spec)
    cut away, or `env_kwargs.obs_radius` on cn, else the identity."""
    if joint_obs:
        return LocalView()
    if local_obs_dim is not None:
        return CentralColumnsView(local_obs_dim)
    radius = env_kwargs.get("obs_radius")
    if radius is None:
        return LocalView()
    if env != "cn":  # the cn builder validates the value; other envs reject the unknown kwarg themselves
        return LocalView()
    return SpreadRadiusView(n_agents, radius)


def local_view_from_config(cfg, spec) -> LocalView:
    """`local_view_for` from a RunConfig and the env's spec (the fully centralised wiring always sees
    everything). The spec is required so that no caller can forget an env's central-only columns."""
    return local_view_for(cfg.env, cfg.n_agents, dict(cfg.env_kwargs), joint_obs=cfg.wiring.joint_obs,
                          local_obs_dim=spec.local_obs_dim)


def spread_hidden_fraction(radius: float, n_agents: int = 3, copies: int = 512, steps: int = 75,
                           seed: int = 0) -> float:
    """The fraction of relative-position slots (landmarks and other agents) a radius hides over
    uniformly random play: the fixed x-axis of the dose-response study
    (docs/results/plan-dose-response.md), computed without any trained policy."""
    from hammer.envs.spread import VecSimpleSpread

    env = VecSimpleSpread(copies, n_agents=n_agents)
    obs, _ = env.reset(seed)
    rng = np.random.default_rng(seed)
    states = [obs]
    for _ in range(steps):
        states.append(env.step(rng.integers(0, 5, (copies, n_agents))).obs)
    return hidden_fraction(np.concatenate(states), radius, n_agents)


def hidden_fraction(obs: np.ndarray, radius: float, n_agents: int) -> float:
    """The fraction of the relative-position slots (landmarks, other agents) of spread observations
    (..., obs_dim) at distance >= radius: what SpreadRadiusView hides."""
    pairs = 2 * n_agents - 1
    rel = obs[..., 4:4 + 2 * pairs].reshape(*obs.shape[:-1], pairs, 2).astype(np.float64)
    return float(np.mean(np.square(rel).sum(axis=-1) >= radius * radius))
