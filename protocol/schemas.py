"""Pydantic models of every message the hammer roles exchange.

Why batched: encoding and decoding a message has a fixed Python cost far above that of its bytes
(`hammer bench codec` prints it), so one message carries all K env copies of one vector step
(arrays have a leading K axis), never one per copy.

numpy arrays are plain `np.ndarray` fields (protocol/fields.py): code builds and reads messages
with numpy directly. The hot types have a second, hand-written validator (protocol/fast_path.py)
that accepts exactly what the models accept; their shape rules are registered at the end here.

Array conventions (K = env copies in this message, N = agents, D = obs dim, M = message length,
A = action vector length):
  LocalObs     obs (K,D) float32, active (K,) bool
  GlobalState  obs (K,N,D) float32, prev_actions (K,N,A) float32, active (K,N) bool
  CentralMsg   msg (K,M) float32 in [-1,1]
  Action       action (K,) int64 (discrete) or (K,A) float32 (continuous), fallback (K,) bool, msg (K,M) float32
  ExperienceChunk  the arrays of protocol/rollout_layout.py
"""

from __future__ import annotations

import hashlib
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from hammer.protocol.dims import Dims, expect, min_max
from hammer.protocol.errors import RangeError, ShapeError
from hammer.protocol.fast_path import Decline, count_nonzero, fast_state, register, set_state
from hammer.protocol.fields import (
    DEFAULT_MAX_BYTES,
    HEADER_BYTES,
    NAME_RE,
    WIRE_DTYPES,
    FiniteFloat,
    MiB,
    Name,
    NDArray,
    NonNegFloat,
    NonNegInt,
    empty_idx,
    field_error,
)
from hammer.protocol.rollout_layout import RolloutLayout
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    Strict,
    StrictBool,
    StrictInt,
    StrictStr,
    field_validator,
    model_validator,
)

SCHEMA_VERSION = 3


# Messages
# --------------------------------------------------------------------------------------------


class Message(BaseModel):
    """Common header of every message.

    `run`, `ts`, `seq` and `sender` are stamped by `HammerSession.publish`; code that builds a
    message only sets `step` and `env_idx` (plus the payload).
    """

    # defer_build: a model's validator is built on its first pydantic validation, so a process builds only
    # those it validates (the hot types mostly go through the fast path below; the edge agent never
    # builds GlobalState or ExperienceChunk).
    model_config = ConfigDict(extra="forbid", arbitrary_types_allowed=False, validate_default=False, defer_build=True)

    TYPE: ClassVar[str] = ""
    MAX_BYTES: ClassVar[int] = DEFAULT_MAX_BYTES

    v: StrictInt = Field(SCHEMA_VERSION, description="schema version (SCHEMA_VERSION)")
    type: StrictStr = Field(description="type tag")
    run: Annotated[str, Strict(), Field(pattern=f"^$|{NAME_RE.pattern}")] = Field(
        "", description="run id; empty only before publishing (the session stamps it)"
    )
    step: NonNegInt = Field(0, description="vector step")
    env_idx: NDArray("int64", 1) = Field(
        default_factory=empty_idx, description="(K,) indices of the env copies this message carries"
    )
    ts: NonNegInt = Field(0, description="send time, ns since the Unix epoch (stamped at publish)")
    seq: NonNegInt = Field(0, description="sequence number of this sender on this key, from 0")
    sender: Annotated[str, Strict(), Field(max_length=128)] = Field("", description="sender name")

    def __init__(self, /, **data: Any) -> None:
        # Hot types first try their hand-written validator (see "Fast path" at the end of this
        # module); whatever it declines goes to pydantic, which accepts it or raises the reference
        # error, so building a message behaves exactly as with pydantic alone, only faster.
        state = fast_state(type(self), data)
        if state is None:
            super().__init__(**data)
        else:
            set_state(self, *state)

    # Mark this __init__ as pydantic's base one, otherwise pydantic would route `model_validate`
    # through it: `model_validate` must stay the pure pydantic reference the fast path is tested against.
    __init__.__pydantic_base_init__ = True  # type: ignore[attr-defined]

    @field_validator("v")
    @classmethod
    def _check_version(cls, v: int) -> int:
        if v != SCHEMA_VERSION:
            raise field_error("version", "v", f"schema version {v}, this code speaks {SCHEMA_VERSION}")
        return v

    @field_validator("env_idx")
    @classmethod
    def _check_env_idx(cls, a: np.ndarray) -> np.ndarray:
        if a.size:
            idx = a.tolist()  # a Python set beats np.unique at K up to a few thousand
            if min(idx) < 0:
                raise field_error("range", "env_idx", "env indices must be >= 0")
            if len(set(idx)) != len(idx):
                raise field_error("shape", "env_idx", "env indices must be unique")
        return a

    @classmethod
    def cap_for_dims(cls, dims: Dims) -> int:
        """The most a valid message of this type can weigh for a receiver that declares `dims`: the
        type's cap, or less where the declared sizes bound every array (a subscription refuses a
        payload beyond it on arrival, before decoding: a flood of oversized payloads costs nothing)."""
        arrays = cls._array_bytes(dims)
        if arrays is None:
            return cls.MAX_BYTES
        return min(cls.MAX_BYTES, HEADER_BYTES + arrays)

    @classmethod
    def _array_bytes(cls, dims: Dims) -> int | None:
        """Bytes of this type's arrays at the sizes `dims` declares (None: not bounded by them)."""
        return None

    @property
    def k(self) -> int:
        """Number of env copies carried."""
        return int(self.env_idx.shape[0])

    def _need(self, field: str, a: np.ndarray | None, shape: tuple) -> None:
        """Raise a shape error when array `a` does not have `shape` (None entries = any)."""
        if a is None:
            return
        actual = a.shape
        if len(actual) != len(shape) or any(s is not None and s != n for s, n in zip(shape, actual)):
            want = "(" + ", ".join("?" if s is None else str(s) for s in shape) + (",)" if len(shape) == 1 else ")")
            raise field_error("shape", field, f"shape {a.shape} disagrees with the message, expected {want} "
                                       f"(K={self.k} from env_idx)")

    def check_dims(self, dims: Dims) -> None:
        """Raise ShapeError/RangeError when the message disagrees with declared dimensions."""
        if dims.num_envs is not None:
            if self.k > dims.num_envs:
                raise ShapeError(f"{self.k} env copies but num_envs is {dims.num_envs}", "env_idx")
            if self.k and (hi := min_max(self.env_idx)[1]) >= dims.num_envs:
                raise RangeError(f"env index {hi} >= num_envs {dims.num_envs}", "env_idx")
        self._check_dims(dims)

    def _check_dims(self, dims: Dims) -> None:
        """Per-type checks against Dims; overridden by subclasses."""

    def _check_agent(self, agent: int, dims: Dims) -> None:
        if dims.n_agents is not None and agent >= dims.n_agents:
            raise RangeError(f"agent {agent} >= n_agents {dims.n_agents}", "agent")


class LocalObs(Message):
    """Env host -> local agent `agent`: its observation in each env copy."""

    TYPE: ClassVar[str] = "local_obs"
    type: Literal["local_obs"] = "local_obs"
    agent: NonNegInt
    obs: NDArray("float32", 2) = Field(description="(K, D) float32")
    active: NDArray("bool", 1) = Field(description="(K,) bool: the agent is present in that copy")
    policy_version: NonNegInt = Field(0, description="policy version the agent must act with (on-policy sync)")

    @classmethod
    def _array_bytes(cls, dims: Dims) -> int | None:
        if dims.num_envs is None or dims.obs_dim is None:
            return None
        return dims.num_envs * (8 + 4 * dims.obs_dim + 1)  # env_idx, obs, active

    @model_validator(mode="after")
    def _shapes(self) -> LocalObs:
        k = self.k
        self._need("obs", self.obs, (k, None))
        self._need("active", self.active, (k,))
        return self

    def _check_dims(self, dims: Dims) -> None:
        self._check_agent(self.agent, dims)
        expect("obs", "obs_dim", self.obs.shape[1], dims.obs_dim)


class GlobalState(Message):
    """Env host -> central agent: all observations and every agent's previous action."""

    TYPE: ClassVar[str] = "global_state"
    type: Literal["global_state"] = "global_state"
    obs: NDArray("float32", 3) = Field(description="(K, N, D) float32")
    prev_actions: NDArray("float32", 3) = Field(
        description="(K, N, A) float32: continuous actions, or for discrete actions a one-hot "
        "(A = n_actions) or the action id as a float (A = 1); zeros on the first step"
    )
    active: NDArray("bool", 2) = Field(description="(K, N) bool")
    policy_version: NonNegInt = Field(0, description="policy version the central agent must use")

    @classmethod
    def _array_bytes(cls, dims: Dims) -> int | None:
        k, n, d, a = dims.num_envs, dims.n_agents, dims.obs_dim, dims.action_dim
        if k is None or n is None or d is None or a is None:
            return None
        return k * (8 + n * (4 * d + 4 * max(a, 1) + 1))  # env_idx, obs, prev_actions, active

    @model_validator(mode="after")
    def _shapes(self) -> GlobalState:
        k, n = self.k, self.obs.shape[1]
        self._need("obs", self.obs, (k, n, None))
        self._need("prev_actions", self.prev_actions, (k, n, None))
        self._need("active", self.active, (k, n))
        return self

    def _check_dims(self, dims: Dims) -> None:
        expect("obs", "n_agents", self.obs.shape[1], dims.n_agents)
        expect("obs", "obs_dim", self.obs.shape[2], dims.obs_dim)
        a = self.prev_actions.shape[2]
        if dims.action_dim is not None and dims.discrete is not None:
            ok = a in (1, dims.action_dim) if dims.discrete else a == dims.action_dim
            if not ok:
                raise ShapeError(f"last dim {a} does not fit action_dim {dims.action_dim}", "prev_actions")


class CentralMsg(Message):
    """Central agent -> local agent `agent`: its message vector in each env copy."""

    TYPE: ClassVar[str] = "central_msg"
    type: Literal["central_msg"] = "central_msg"
    agent: NonNegInt
    msg: NDArray("float32", 2) = Field(description="(K, M) float32 in [-1, 1]")
    policy_version: NonNegInt = 0

    @classmethod
    def _array_bytes(cls, dims: Dims) -> int | None:
        if dims.num_envs is None or dims.msg_dim is None:
            return None
        return dims.num_envs * (8 + 4 * dims.msg_dim)  # env_idx, msg

    @model_validator(mode="after")
    def _shapes(self) -> CentralMsg:
        self._need("msg", self.msg, (self.k, None))
        if self.msg.size and (self.msg.min() < -1.0 or self.msg.max() > 1.0):
            raise field_error("range", "msg", "message values must lie in [-1, 1]")
        return self

    def _check_dims(self, dims: Dims) -> None:
        self._check_agent(self.agent, dims)
        expect("msg", "msg_dim", self.msg.shape[1], dims.msg_dim)


class Action(Message):
    """Local agent `agent` -> env host: its action in each env copy."""

    TYPE: ClassVar[str] = "action"
    type: Literal["action"] = "action"
    agent: NonNegInt
    action: NDArray(("int64", "float32"), (1, 2)) = Field(
        description="(K,) int64 action ids, or (K, A) float32 continuous actions"
    )
    policy_version: NonNegInt = 0
    fallback: NDArray("bool", 1) | None = Field(
        None, description="(K,) the central message was late and a fallback was used (None = all False)"
    )
    msg: NDArray("float32", 2) | None = Field(
        None, description="(K, M) float32: the message the agent acted on (received or fallback)"
    )

    @classmethod
    def _array_bytes(cls, dims: Dims) -> int | None:
        k, a, m = dims.num_envs, dims.action_dim, dims.msg_dim
        if k is None or a is None or m is None or dims.discrete is None:
            return None
        return k * (8 + (8 if dims.discrete else 4 * a) + 1 + 4 * m)  # env_idx, action, fallback, msg

    @model_validator(mode="after")
    def _shapes(self) -> Action:
        k = self.k
        if self.action.dtype == np.int64:
            self._need("action", self.action, (k,))
        else:
            self._need("action", self.action, (k, None))
        if self.fallback is None:
            self.fallback = np.zeros(k, dtype=bool)
        self._need("fallback", self.fallback, (k,))
        self._need("msg", self.msg, (k, None))
        return self

    @property
    def discrete(self) -> bool:
        return self.action.dtype == np.int64

    def _check_dims(self, dims: Dims) -> None:
        self._check_agent(self.agent, dims)
        if self.msg is not None:
            expect("msg", "msg_dim", self.msg.shape[1], dims.msg_dim)
        check_actions(self.action, dims)


def check_actions(action: np.ndarray, dims: Dims) -> None:
    """An `action` field against declared dims (an action's, an uplink's): ids or vectors as declared,
    ids within the action count, vectors of the declared length."""
    discrete = action.dtype == np.int64
    if dims.discrete is not None and dims.discrete != discrete:
        want = "(K,) int64 ids" if dims.discrete else "(K, A) float32 vectors"
        raise ShapeError(f"actions must be {want}, got {action.dtype} {action.shape}", "action")
    if dims.action_dim is None:
        return
    if discrete:
        if action.size:
            lo, hi = min_max(action)
            if lo < 0 or hi >= dims.action_dim:
                raise RangeError(f"action ids must be in [0, {dims.action_dim})", "action")
    else:
        expect("action", "action vector length", action.shape[1], dims.action_dim)


ArrayName = Annotated[str, Strict(), Field(pattern=r"^[A-Za-z_][A-Za-z0-9_.]{0,63}$")]
Scalar = StrictBool | StrictInt | FiniteFloat | Annotated[str, Strict(), Field(max_length=256)] | None


class ExperienceChunk(Message):
    """An actor -> its learner: named arrays of experience tagged with the producing policy version.

    Role "team" (the env host): one rollout, the arrays of `rollout_layout.CHUNK`; role "central"
    (the central agent): one vector step's record, the arrays of `rollout_layout.RECORD` for the
    K copies of env_idx. The codec always enforces the dtype whitelist, finiteness and at most 64
    arrays; a receiver that declares every size of the layout (`Dims.from_layout`) also gets each
    array's name, dtype and shape checked, so a chunk that would train on misread numbers is
    rejected and counted like any other bad message.
    """

    TYPE: ClassVar[str] = "experience"
    MAX_BYTES: ClassVar[int] = 64 * MiB
    type: Literal["experience"] = "experience"
    role: Name
    policy_version: NonNegInt
    arrays: dict[ArrayName, NDArray(tuple(WIRE_DTYPES))] = Field(max_length=64)
    meta: dict[ArrayName, Scalar] = Field(default_factory=dict, max_length=64)

    RECORD_ROLE: ClassVar[str] = "central"

    @classmethod
    def cap_for(cls, layout: RolloutLayout) -> int:
        """The size cap of one run's rollout chunk: the default cap, or the chunk's arrays plus 1 MiB
        of framing when they are larger (cn with N=50 agents: ~100 MB per update). Sender and learner
        both derive it from the run's layout, so a payload beyond it is still refused on arrival."""
        return max(cls.MAX_BYTES, layout.chunk_nbytes() + MiB)

    def _check_dims(self, dims: Dims) -> None:
        layout = dims.rollout_layout()
        if layout is None:
            return
        if self.role == self.RECORD_ROLE:
            layout.check_record(self.arrays, k=self.k)
        else:
            layout.check_chunk(self.arrays)


class Weights(Message):
    """A learner -> actors: a policy version as a safetensors blob with its sha256."""

    TYPE: ClassVar[str] = "weights"
    MAX_BYTES: ClassVar[int] = 256 * MiB
    type: Literal["weights"] = "weights"
    role: Name
    version: NonNegInt
    format: Literal["safetensors"] = "safetensors"
    blob: Annotated[bytes, Strict()]
    sha256: Annotated[str, Strict(), Field(pattern=r"^[0-9a-f]{64}$")]

    @model_validator(mode="after")
    def _digest(self) -> Weights:
        if hashlib.sha256(self.blob).hexdigest() != self.sha256:
            raise field_error("checksum", "sha256", "sha256 of blob does not match (corrupted or truncated weights)")
        return self

    @classmethod
    def from_blob(cls, role: str, version: int, blob: bytes, **header: Any) -> Weights:
        """Build a Weights message computing the sha256 of `blob`."""
        return cls(role=role, version=version, blob=blob, sha256=hashlib.sha256(blob).hexdigest(), **header)


# Only what something sends and something handles: the launcher and the env host end a run.
ControlCommand = Literal["stop"]


class Control(Message):
    """Launcher -> roles: a command with small arguments."""

    TYPE: ClassVar[str] = "control"
    type: Literal["control"] = "control"
    command: ControlCommand
    target: Annotated[str, Strict(), Field(pattern=f"^\\*$|{NAME_RE.pattern}")] = Field(
        "*", description="role name, or * for every role"
    )
    args: dict[ArrayName, Scalar] = Field(default_factory=dict, max_length=32)


HeartbeatStatus = Literal["starting", "ready", "running", "paused", "stopping", "stopped", "error"]


class Heartbeat(Message):
    """Any role -> launcher: alive, what it is doing, a few counters."""

    TYPE: ClassVar[str] = "heartbeat"
    type: Literal["heartbeat"] = "heartbeat"
    role: Name
    pid: NonNegInt
    status: HeartbeatStatus
    counters: dict[ArrayName, NonNegInt | NonNegFloat] = Field(
        default_factory=dict, max_length=64,
        description="totals since the process started: finite, >= 0, never falling for one role and pid "
                    "(a receiver refuses a heartbeat whose counters fall)")
    gauges: dict[ArrayName, StrictInt | FiniteFloat] = Field(
        default_factory=dict, max_length=16,
        description="current values that may move either way (policy version, latency percentiles, a running metric)")
    detail: Annotated[str, Strict(), Field(max_length=1024)] = ""


class Uplink(Message):
    """Robot `agent` -> central agent, in a fleet (docs/fleet.md): what the robot's own sensors saw
    and the action it took last, so the central agent can build its state without a simulator.
    `seq` and `ts` (stamped at publish) order and date it; the central agent dates it by arrival."""

    TYPE: ClassVar[str] = "uplink"
    type: Literal["uplink"] = "uplink"
    agent: NonNegInt
    obs: NDArray("float32", 2) = Field(description="(K, D) float32: the robot's observation")
    action: NDArray(("int64", "float32"), (1, 2)) | None = Field(
        None, description="(K,) int64 ids or (K, A) float32: the robot's previous action (None: none yet)"
    )

    @classmethod
    def _array_bytes(cls, dims: Dims) -> int | None:
        k, d, a = dims.num_envs, dims.obs_dim, dims.action_dim
        if k is None or d is None or a is None or dims.discrete is None:
            return None
        return k * (8 + 4 * d + (8 if dims.discrete else 4 * a))  # env_idx, obs, action

    @model_validator(mode="after")
    def _shapes(self) -> Uplink:
        self._need("obs", self.obs, (self.k, None))
        if self.action is not None:
            self._need("action", self.action, (self.k,) if self.action.dtype == np.int64 else (self.k, None))
        return self

    def _check_dims(self, dims: Dims) -> None:
        self._check_agent(self.agent, dims)
        expect("obs", "obs_dim", self.obs.shape[1], dims.obs_dim)
        if self.action is not None:
            check_actions(self.action, dims)


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.TYPE: cls
    for cls in (LocalObs, GlobalState, CentralMsg, Action, ExperienceChunk, Weights, Control, Heartbeat, Uplink)
}


def json_schemas() -> dict[str, Any]:
    """JSON Schema (validation side) of every message type, keyed by type tag."""
    return {
        "schema_version": SCHEMA_VERSION,
        "messages": {tag: cls.model_json_schema() for tag, cls in MESSAGE_TYPES.items()},
    }


def _local_obs_shapes(v: dict, k: int) -> None:
    if v["obs"].shape[0] != k or v["active"].shape[0] != k:
        raise Decline


def _global_state_shapes(v: dict, k: int) -> None:
    obs, prev = v["obs"].shape, v["prev_actions"].shape
    if obs[0] != k or prev[0] != k or prev[1] != obs[1] or v["active"].shape != obs[:2]:
        raise Decline


def _central_msg_shapes(v: dict, k: int) -> None:
    m = v["msg"]
    if m.shape[0] != k or count_nonzero(np.abs(m) <= 1.0) != m.size:
        raise Decline


def _action_shapes(v: dict, k: int) -> str | None:
    a = v["action"]
    if a.shape[0] != k or a.ndim != (1 if a.dtype == np.int64 else 2):
        raise Decline
    for name in ("fallback", "msg"):
        x = v[name]
        if x is not None and x.shape[0] != k:
            raise Decline
    if v["fallback"] is None:
        v["fallback"] = np.zeros(k, dtype=bool)
        return "fallback"
    return None


for _cls, _shapes in ((LocalObs, _local_obs_shapes), (GlobalState, _global_state_shapes),
                      (CentralMsg, _central_msg_shapes), (Action, _action_shapes)):
    register(_cls, _shapes)
