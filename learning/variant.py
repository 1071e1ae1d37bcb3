"""What a run's variant and central mode mean for every part of the system, decided once.

The paper's comparisons differ in how the team is wired: who sends messages, whether a central
network exists and how it learns, what a local agent observes. Every runner (in-process trainer,
env host, central agent, local agents, learner, launcher) asks this object instead of comparing
`variant` / `central_mode` strings itself, so adding a variant is one change here.
Torch-free and import-light: the edge local agent uses it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from hammer.learning.config import RunConfig

VARIANTS = ("hammer", "il", "random", "centralized")
CENTRAL_MODES = ("rl", "backprop")
MESSAGE_VARIANTS = ("hammer", "random")  # the local agents receive a message vector


@dataclass(frozen=True)
class Wiring:
    variant: str
    central_mode: str
    n_agents: int
    msg_dim: int  # what the local agents receive: 0 for il and centralized
    msg_dropout: float = 0.0
    central_net: str = "concat"

    @classmethod
    def from_config(cls, cfg: RunConfig) -> Wiring:
        msg_dim = cfg.msg_dim if cfg.variant in MESSAGE_VARIANTS else 0
        return cls(cfg.variant, cfg.central_mode, cfg.n_agents, msg_dim, cfg.msg_dropout, cfg.central_net)

    @property
    def uses_central(self) -> bool:
        """A central agent sends each local agent a message every step (learned or random)."""
        return self.variant in MESSAGE_VARIANTS

    @property
    def has_central_network(self) -> bool:
        """The messages come from a trained central network (HAMMER)."""
        return self.variant == "hammer"

    @property
    def set_central(self) -> bool:
        """The central network is the permutation-invariant one (`networks.SetCentralAgent`: a
        per-agent encoder shared by all agents, attention across them) instead of the paper's
        network over the concatenated state."""
        return self.has_central_network and self.central_net == "set"

    @property
    def central_rl(self) -> bool:
        """The central network is trained by its own PPO on Gaussian messages (the paper's text)."""
        return self.has_central_network and self.central_mode == "rl"

    @property
    def central_backprop(self) -> bool:
        """The local agents' loss is back-propagated through the message (the authors' code)."""
        return self.has_central_network and self.central_mode == "backprop"

    @property
    def random_messages(self) -> bool:
        return self.variant == "random"

    @property
    def joint_obs(self) -> bool:
        """Each local agent observes every agent's observation plus one-hot(its index) (centralised)."""
        return self.variant == "centralized"

    @property
    def needs_central_record(self) -> bool:
        """The learner needs what only the central agent knows of each step: the Gaussian sample,
        its log-density and value (rl), or which messages were dropped (message dropout)."""
        return self.central_rl or (self.uses_central and self.msg_dropout > 0)

    def local_obs_dim(self, obs_dim: int) -> int:
        """Width of the observation a local agent receives from the env host."""
        return obs_dim * self.n_agents if self.joint_obs else obs_dim

    def local_input_dim(self, obs_dim: int) -> int:
        """Width of the local policy's input: observation, one-hot index (centralised), message."""
        if self.joint_obs:
            return self.n_agents * obs_dim + self.n_agents
        return obs_dim + self.msg_dim

    @property
    def label(self) -> str:
        """`hammer-rl`, `hammer-backprop`, `il`, `random`, `centralized`; `hammer-rl-set` with the
        set central network (the paper's network keeps the plain label)."""
        if not self.has_central_network:
            return self.variant
        return f"{self.variant}-{self.central_mode}" + ("-set" if self.set_central else "")
