"""The rollout layout: every array of one rollout, with its shape and dtype, declared once.

Three parties handle a rollout: the env host assembles it and sends it to the learner as one
ExperienceChunk, the central agent sends the learner a per-step record of what only it knows
(its Gaussian sample, log-density, value, which messages it dropped), and the learner (like the
in-process trainer) fills its PPO buffer from both plus what it computes itself (log-probs,
values, global states). A shape or dtype that differs between them would not fail loudly: it
would train on the wrong numbers. So the arrays are listed here, once, with symbolic shapes, and
each party allocates or checks against this list.

Symbols: T rollout steps, K env copies, N agents, D observation length, A action width (number of
discrete actions: the one-hot width of a previous action; or the continuous action length),
M message length, S global-state length (learner only). `a` in a shape is the action shape:
nothing for discrete action ids, (A,) for continuous actions; dtype "action" is int64 for
discrete ids, float32 for continuous actions.

Torch-free and free of the config: the protocol checks received chunks with it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from hammer.protocol.errors import DTypeError, FieldError, ShapeError

if TYPE_CHECKING:  # numpy is imported where a layout is used, not on the wire path (the lite edge agent)
    import numpy as np


@dataclass(frozen=True)
class ArraySpec:
    name: str
    shape: str  # one symbol per axis, see the module docstring
    dtype: str  # a wire dtype name, or "action"
    fill: float = 0.0  # initial value where an array is allocated


# Env host -> learner, once per rollout (ExperienceChunk, role "team").
CHUNK = (
    ArraySpec("obs", "TKND", "float32"),
    ArraySpec("prev", "TKNA", "float32"),  # previous actions as the central agent saw them; 0 after a reset
    ArraySpec("msg", "TKNM", "float32"),  # what each local agent acted on (received or fallback)
    ArraySpec("actions", "TKNa", "action"),
    ArraySpec("rewards", "TKN", "float32"),
    ArraySpec("terminated", "TKN", "bool"),
    ArraySpec("truncated", "TKN", "bool"),
    ArraySpec("active", "TKN", "bool"),
    ArraySpec("reset", "TKN", "bool"),  # the copy was reset after this step
    ArraySpec("final_obs", "TKND", "float32"),  # where reset: the episode's last observation
    ArraySpec("final_prev", "TKNA", "float32"),  # where reset: the actions of its last step
    ArraySpec("defaulted", "TKN", "bool"),  # the agent's action missed the deadline: the default was used
    ArraySpec("steps", "T", "int64"),  # global vector step of each t (joins the central records)
    ArraySpec("last_obs", "KND", "float32"),  # where the next rollout starts (bootstrap values)
    ArraySpec("last_prev", "KNA", "float32"),
)

# Central agent -> learner, once per vector step (ExperienceChunk, role "central").
RECORD = (
    ArraySpec("msg_raw", "KNM", "float32"),  # the unclipped Gaussian sample (rl); its logp is trained
    ArraySpec("c_logp", "KN", "float32"),
    ArraySpec("c_values", "KN", "float32"),
    ArraySpec("keep", "KN", "bool"),  # message not dropped
)

# The learner's PPO buffer (learning.rollout.RolloutBuffer), filled by the in-process trainer as it
# acts, or by the learner from a chunk and its records.
BUFFER = (
    ArraySpec("obs", "TKND", "float32"),
    ArraySpec("state", "TKS", "float32"),
    ArraySpec("msg", "TKNM", "float32"),
    ArraySpec("msg_raw", "TKNM", "float32"),
    ArraySpec("keep", "TKN", "float32", fill=1.0),
    ArraySpec("actions", "TKNa", "action"),
    ArraySpec("logp", "TKN", "float32"),
    ArraySpec("values", "TKN", "float32"),
    ArraySpec("c_logp", "TKN", "float32"),
    ArraySpec("c_values", "TKN", "float32"),
    ArraySpec("rewards", "TKN", "float32"),
    ArraySpec("terminated", "TKN", "bool"),
    ArraySpec("truncated", "TKN", "bool"),
    ArraySpec("active", "TKN", "bool"),
    ArraySpec("reset", "TKN", "bool"),
    ArraySpec("final_values", "TKN", "float32"),  # V(final_obs) where reset
    ArraySpec("c_final_values", "TKN", "float32"),
)


@dataclass(frozen=True)
class RolloutLayout:
    """The sizes the symbols stand for in one run."""

    t: int
    k: int
    n: int
    obs_dim: int
    action_dim: int
    msg_dim: int
    discrete: bool
    state_dim: int = 0  # only the learner's buffer has global states

    @classmethod
    def from_config(cls, cfg: Any, spec: Any, state_dim: int = 0) -> RolloutLayout:
        """From a RunConfig and an EnvSpec (duck-typed: the protocol does not import the config)."""
        return cls(cfg.rollout_steps, cfg.num_envs, cfg.n_agents, spec.obs_dim, spec.action_dim,
                   cfg.wiring.msg_dim, spec.discrete, state_dim)

    @property
    def action_shape(self) -> tuple[int, ...]:
        return () if self.discrete else (self.action_dim,)

    def sizes(self, **override: int) -> dict[str, int]:
        """Symbol -> size (`override` e.g. K=2 for a record carrying two env copies)."""
        return {"T": self.t, "K": self.k, "N": self.n, "D": self.obs_dim, "A": self.action_dim,
                "M": self.msg_dim, "S": self.state_dim, **override}

    def shape(self, spec: ArraySpec, **override: int) -> tuple[int, ...]:
        return resolve_shape(spec, self.sizes(**override), self.action_shape)

    def dtype(self, spec: ArraySpec) -> np.dtype:
        return resolve_dtype(spec, self.discrete)

    def allocate(self, specs: tuple[ArraySpec, ...]) -> dict[str, np.ndarray]:
        return allocate(specs, self.sizes(), self.action_shape, self.discrete)

    def chunk_nbytes(self) -> int:
        """The bytes of a chunk's arrays (without the message's framing): what sizes its cap."""
        import math

        return sum(math.prod(self.shape(s)) * self.dtype(s).itemsize for s in CHUNK)

    def chunk_steps(self) -> dict[str, np.ndarray]:
        """The per-step arrays of a chunk (leading T), which the env host fills as it steps."""
        return self.allocate(tuple(s for s in CHUNK if s.shape.startswith("T")))

    def check_chunk(self, arrays: dict[str, np.ndarray]) -> None:
        """Raise a ProtocolError naming the array when `arrays` is not a rollout of this layout."""
        self._check(CHUNK, arrays)

    def check_record(self, arrays: dict[str, np.ndarray], k: int | None = None) -> None:
        """As check_chunk, for one central record carrying `k` env copies (all of them by default)."""
        self._check(RECORD, arrays, **({} if k is None else {"K": k}))

    def _check(self, specs: tuple[ArraySpec, ...], arrays: dict[str, np.ndarray], **override: int) -> None:
        names = {s.name for s in specs}
        missing, extra = sorted(names - set(arrays)), sorted(set(arrays) - names)
        if missing or extra:
            what = "; ".join(filter(None, (missing and f"lacks {missing}", extra and f"has unknown {extra}")))
            raise FieldError(f"{what} (rollout layout)", "arrays")
        for s in specs:
            a, shape, dtype = arrays[s.name], self.shape(s, **override), self.dtype(s)
            if a.dtype != dtype:
                raise DTypeError(f"dtype {a.dtype}, the rollout layout needs {dtype}", f"arrays.{s.name}")
            if a.shape != shape:
                raise ShapeError(f"shape {a.shape}, the rollout layout needs {shape}", f"arrays.{s.name}")


def resolve_shape(spec: ArraySpec, sizes: dict[str, int], action_shape: tuple[int, ...]) -> tuple[int, ...]:
    return tuple(n for sym in spec.shape for n in (action_shape if sym == "a" else (sizes[sym],)))


def resolve_dtype(spec: ArraySpec, discrete: bool) -> np.dtype:
    import numpy as np

    if spec.dtype == "action":
        return np.dtype(np.int64 if discrete else np.float32)
    return np.dtype(spec.dtype)


def allocate(specs: tuple[ArraySpec, ...], sizes: dict[str, int], action_shape: tuple[int, ...],
             discrete: bool) -> dict[str, np.ndarray]:
    """Name -> a new array of that spec, every element `spec.fill`."""
    import numpy as np

    return {s.name: np.full(resolve_shape(s, sizes, action_shape), s.fill, resolve_dtype(s, discrete)) for s in specs}
