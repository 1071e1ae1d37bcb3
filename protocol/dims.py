"""What a receiver declares it expects of a message's sizes (`Dims`) and the checks against it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from hammer.protocol.errors import ShapeError

if TYPE_CHECKING:  # numpy is not imported on the lite edge path (protocol/fields.py)
    from hammer.protocol.rollout_layout import RolloutLayout


@dataclass(frozen=True)
class Dims:
    """Dimensions a receiver expects; None means "do not check".

    num_envs: total env copies (env_idx < num_envs, K <= num_envs); n_agents: N; obs_dim: D;
    msg_dim: M; action_dim: number of discrete actions, or length of the continuous action vector;
    discrete: whether actions are discrete ids (int64) or continuous vectors (float32);
    rollout_steps: T of an experience chunk. With all seven declared, experience chunks are
    checked array by array against the rollout layout (`rollout_layout`). site_dim: C, the columns
    of a fleet's site feed (what no robot observes). echo: an action must
    carry the message it acted on (an env host that trains records it; serving needs none).
    """

    num_envs: int | None = None
    n_agents: int | None = None
    obs_dim: int | None = None
    msg_dim: int | None = None
    action_dim: int | None = None
    discrete: bool | None = None
    rollout_steps: int | None = None
    echo: bool | None = None
    site_dim: int | None = None

    @classmethod
    def from_layout(cls, layout: RolloutLayout) -> Dims:
        """What a learner declares: every size of the rollout layout."""
        return cls(layout.k, layout.n, layout.obs_dim, layout.msg_dim, layout.action_dim, layout.discrete, layout.t)

    def rollout_layout(self) -> RolloutLayout | None:
        """The rollout layout these dims declare, or None when a size of it is not declared."""
        sizes = (self.rollout_steps, self.num_envs, self.n_agents, self.obs_dim, self.action_dim, self.msg_dim,
                 self.discrete)
        if any(x is None for x in sizes):
            return None
        from hammer.protocol.rollout_layout import RolloutLayout

        return RolloutLayout(*sizes)


def min_max(a: Any) -> tuple[int, int]:
    """Min and max of a non-empty int array. Small arrays go through a list: a process that just
    woke up runs numpy's reduction machinery cache-cold, slower than a list's min and max at K=32
    (`hammer bench codec --cold`)."""
    if a.size <= 1024:
        values = a.ravel().tolist() if hasattr(a, "ravel") else a.tolist(flat=True)  # numpy's, or a WireArray
        return min(values), max(values)
    return int(a.min()), int(a.max())


def expect(field: str, what: str, actual: int, expected: int | None) -> None:
    if expected is not None and actual != expected:
        raise ShapeError(f"{what} is {actual}, expected {expected} (declared Dims)", field)
