"""Pydantic models of every message the hammer roles exchange.

Why batched: encoding and decoding a message has a fixed Python cost far above that of its bytes
(`hammer bench codec` prints it), so one message carries all K env copies of one vector step
(arrays have a leading K axis), never one per copy.

numpy arrays are plain `np.ndarray` fields: code builds and reads messages with numpy directly.
The same validators run when a message is built in Python and when it is decoded from the wire,
so a NaN or a wrong dtype is caught at the sender as well as at the receiver.

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
import re
import sys
import typing
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from hammer.protocol.errors import RangeError, ShapeError
from hammer.protocol.rollout_layout import RolloutLayout
from pydantic import (
    AllowInfNan,
    BaseModel,
    ConfigDict,
    Field,
    GetCoreSchemaHandler,
    GetJsonSchemaHandler,
    Strict,
    StrictBool,
    StrictInt,
    StrictStr,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError, core_schema

SCHEMA_VERSION = 3

# dtype names on the wire -> numpy dtype (always little-endian on the wire).
WIRE_DTYPES: dict[str, np.dtype] = {
    "float32": np.dtype("<f4"),
    "float64": np.dtype("<f8"),
    "int64": np.dtype("<i8"),
    "int32": np.dtype("<i4"),
    "uint8": np.dtype("u1"),
    "bool": np.dtype("?"),
}
FLOAT_DTYPES = frozenset({"float32", "float64"})
_NATIVE: dict[str, np.dtype] = {name: dt.newbyteorder("=") for name, dt in WIRE_DTYPES.items()}
# dtype -> wire name, looked up by dtype object because `dtype.name` is slow Python code.
_NAME_OF: dict[np.dtype, str] = {dt: name for name, dt in WIRE_DTYPES.items()}


def dtype_name(dt: np.dtype) -> str:
    """Wire name of a numpy dtype, or its numpy name when it is not on the whitelist."""
    name = _NAME_OF.get(dt)
    if name is None:
        name = _NAME_OF.get(dt.newbyteorder("<"), dt.name) if dt.byteorder == ">" else dt.name
    return name
MAX_NDIM = 8

MiB = 1 << 20
DEFAULT_MAX_BYTES = 4 * MiB
# Everything of a message but its array bytes, bounded: field names, ints, the type tag, run id
# (<= 64 chars), sender (<= 128) and up to four array maps ({"dtype", "shape" (<= 8 ints), "data"}).
HEADER_BYTES = 2048

NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
NAME_RULE = "1-64 chars of letters, digits, '_', '-', '.', starting with a letter or digit"


def _err(reason: str, field: str | None, msg: str) -> PydanticCustomError:
    """A pydantic error whose type is a protocol `reason`; the codec maps it to a ProtocolError."""
    # The field name is in the text too: model-level errors have no `loc` in pydantic's message.
    return PydanticCustomError(reason, "{field}: {msg}" if field else "{msg}", {"msg": msg, "field": field or ""})


def check_name(value: str, what: str) -> str:
    """Validate a run id / role name used inside key expressions (raises ValueError)."""
    if not isinstance(value, str) or not NAME_RE.match(value):
        raise ValueError(f"invalid {what} {value!r}: use {NAME_RULE}")
    return value


# --------------------------------------------------------------------------------------------
# numpy array fields
# --------------------------------------------------------------------------------------------


def array_to_wire(a: np.ndarray) -> dict[str, Any]:
    """The wire map of an array: {"dtype": name, "shape": [..], "data": raw little-endian bytes}."""
    name = dtype_name(a.dtype)
    wire = WIRE_DTYPES.get(name)
    if wire is None:
        raise _err("dtype", None, f"dtype {name} is not allowed on the wire ({', '.join(WIRE_DTYPES)})")
    if a.dtype.byteorder == ">":
        a = a.astype(wire)
    # tobytes() always writes C order, whatever the memory layout of `a`.
    return {"dtype": name, "shape": list(a.shape), "data": a.tobytes()}


def _array_from_wire(d: dict, field: str | None) -> np.ndarray:
    if len(d) != 3 or "dtype" not in d or "shape" not in d or "data" not in d:
        raise _err("field", field, f"array map must have exactly keys dtype, shape, data; got {sorted(d)}")
    name, shape, data = d["dtype"], d["shape"], d["data"]
    if not isinstance(name, str) or name not in WIRE_DTYPES:
        raise _err("dtype", field, f"dtype {name!r} is not allowed ({', '.join(WIRE_DTYPES)})")
    if (
        not isinstance(shape, list)
        or len(shape) > MAX_NDIM
        or not all(type(n) is int and n >= 0 for n in shape)
    ):
        raise _err("shape", field, f"shape must be a list of at most {MAX_NDIM} non-negative ints, got {shape!r}")
    if not isinstance(data, bytes):
        raise _err("field", field, f"array data must be msgpack bin, got {type(data).__name__}")
    dtype = WIRE_DTYPES[name]
    count = 1
    for n in shape:
        count *= n
    if count * dtype.itemsize != len(data):
        raise _err("shape", field, f"shape {shape} of {name} needs {count * dtype.itemsize} bytes, got {len(data)}")
    if name == "bool" and data and max(data) > 1:
        raise _err("field", field, "bool array bytes must be 0 or 1")
    # astype(native, copy=True): decoded arrays are native-endian, writable and do not pin the buffer.
    return np.frombuffer(data, dtype=dtype).reshape(shape).astype(_NATIVE[name], copy=True)


@dataclass(frozen=True)
class _ArrayField:
    """Pydantic annotation for an np.ndarray field with allowed dtypes and ranks."""

    dtypes: tuple[str, ...]
    ndims: tuple[int, ...] | None

    def validate(self, value: Any, info: core_schema.ValidationInfo) -> np.ndarray:
        field = info.field_name
        if isinstance(value, dict):
            a = _array_from_wire(value, field)
        elif isinstance(value, np.ndarray):
            a = value
        else:
            raise _err("field", field, f"expected a numpy array (or wire array map), got {type(value).__name__}")
        name = dtype_name(a.dtype)
        if name not in self.dtypes:
            hint = f"; cast with .astype(np.{self.dtypes[0]})" if self.dtypes[0] != "bool" else ""
            raise _err("dtype", field, f"dtype {name} not allowed here, need one of {list(self.dtypes)}{hint}")
        if self.ndims is not None and a.ndim not in self.ndims:
            raise _err("shape", field, f"needs {' or '.join(map(str, self.ndims))} dims, got shape {a.shape}")
        if a.ndim > MAX_NDIM:
            raise _err("shape", field, f"at most {MAX_NDIM} dims, got {a.ndim}")
        if name in FLOAT_DTYPES and not np.isfinite(a).all():
            raise _err("nonfinite", field, "holds NaN or inf")
        return a

    def __get_pydantic_core_schema__(self, source: Any, handler: GetCoreSchemaHandler) -> core_schema.CoreSchema:
        return core_schema.with_info_plain_validator_function(self.validate)

    def __get_pydantic_json_schema__(self, schema: core_schema.CoreSchema, handler: GetJsonSchemaHandler) -> dict:
        desc = f"numpy array, dtype {' or '.join(self.dtypes)}"
        if self.ndims is not None:
            desc += f", {' or '.join(map(str, self.ndims))} dims"
        return {
            "type": "object",
            "description": desc + "; raw bytes are little-endian, C order",
            "properties": {
                "dtype": {"type": "string", "enum": list(self.dtypes)},
                "shape": {"type": "array", "items": {"type": "integer", "minimum": 0}, "maxItems": MAX_NDIM},
                "data": {"type": "string", "format": "binary"},
            },
            "required": ["dtype", "shape", "data"],
            "additionalProperties": False,
        }


def NDArray(dtypes: str | tuple[str, ...], ndims: int | tuple[int, ...] | None = None) -> Any:
    """An np.ndarray field type: `NDArray("float32", 2)` is a float32 matrix."""
    dts = (dtypes,) if isinstance(dtypes, str) else tuple(dtypes)
    nds = (ndims,) if isinstance(ndims, int) else ndims
    return Annotated[np.ndarray, _ArrayField(dts, nds)]


NonNegInt = Annotated[int, Strict(), Field(ge=0)]
FiniteFloat = Annotated[float, Strict(), AllowInfNan(False)]
NonNegFloat = Annotated[float, Strict(), AllowInfNan(False), Field(ge=0)]
Name = Annotated[str, Strict(), Field(pattern=NAME_RE.pattern)]


def _empty_idx() -> np.ndarray:
    return np.zeros(0, dtype=np.int64)


# --------------------------------------------------------------------------------------------
# Declared dimensions a receiver can check messages against
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Dims:
    """Dimensions a receiver expects; None means "do not check".

    num_envs: total env copies (env_idx < num_envs, K <= num_envs); n_agents: N; obs_dim: D;
    msg_dim: M; action_dim: number of discrete actions, or length of the continuous action vector;
    discrete: whether actions are discrete ids (int64) or continuous vectors (float32);
    rollout_steps: T of an experience chunk. With all seven declared, experience chunks are
    checked array by array against the rollout layout (`rollout_layout`).
    """

    num_envs: int | None = None
    n_agents: int | None = None
    obs_dim: int | None = None
    msg_dim: int | None = None
    action_dim: int | None = None
    discrete: bool | None = None
    rollout_steps: int | None = None

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
        return RolloutLayout(*sizes)


def _min_max(a: np.ndarray) -> tuple[int, int]:
    """Min and max of a non-empty int array. Small arrays go through a list: a process that just
    woke up runs numpy's reduction machinery cache-cold, slower than a list's min and max at K=32
    (`hammer bench codec --cold`)."""
    if a.size <= 1024:
        values = a.ravel().tolist()
        return min(values), max(values)
    return int(a.min()), int(a.max())


def _expect(field: str, what: str, actual: int, expected: int | None) -> None:
    if expected is not None and actual != expected:
        raise ShapeError(f"{what} is {actual}, expected {expected} (declared Dims)", field)


# --------------------------------------------------------------------------------------------
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
        default_factory=_empty_idx, description="(K,) indices of the env copies this message carries"
    )
    ts: NonNegInt = Field(0, description="send time, ns since the Unix epoch (stamped at publish)")
    seq: NonNegInt = Field(0, description="sequence number of this sender on this key, from 0")
    sender: Annotated[str, Strict(), Field(max_length=128)] = Field("", description="sender name")

    def __init__(self, /, **data: Any) -> None:
        # Hot types first try their hand-written validator (see "Fast path" at the end of this
        # module); whatever it declines goes to pydantic, which accepts it or raises the reference
        # error, so building a message behaves exactly as with pydantic alone, only faster.
        state = _fast_state(type(self), data)
        if state is None:
            super().__init__(**data)
        else:
            _set_state(self, *state)

    # Mark this __init__ as pydantic's base one, otherwise pydantic would route `model_validate`
    # through it: `model_validate` must stay the pure pydantic reference the fast path is tested against.
    __init__.__pydantic_base_init__ = True  # type: ignore[attr-defined]

    @field_validator("v")
    @classmethod
    def _check_version(cls, v: int) -> int:
        if v != SCHEMA_VERSION:
            raise _err("version", "v", f"schema version {v}, this code speaks {SCHEMA_VERSION}")
        return v

    @field_validator("env_idx")
    @classmethod
    def _check_env_idx(cls, a: np.ndarray) -> np.ndarray:
        if a.size:
            idx = a.tolist()  # a Python set beats np.unique at K up to a few thousand
            if min(idx) < 0:
                raise _err("range", "env_idx", "env indices must be >= 0")
            if len(set(idx)) != len(idx):
                raise _err("shape", "env_idx", "env indices must be unique")
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
            raise _err("shape", field, f"shape {a.shape} disagrees with the message, expected {want} "
                                       f"(K={self.k} from env_idx)")

    def check_dims(self, dims: Dims) -> None:
        """Raise ShapeError/RangeError when the message disagrees with declared dimensions."""
        if dims.num_envs is not None:
            if self.k > dims.num_envs:
                raise ShapeError(f"{self.k} env copies but num_envs is {dims.num_envs}", "env_idx")
            if self.k and (hi := _min_max(self.env_idx)[1]) >= dims.num_envs:
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
        _expect("obs", "obs_dim", self.obs.shape[1], dims.obs_dim)


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
        _expect("obs", "n_agents", self.obs.shape[1], dims.n_agents)
        _expect("obs", "obs_dim", self.obs.shape[2], dims.obs_dim)
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
            raise _err("range", "msg", "message values must lie in [-1, 1]")
        return self

    def _check_dims(self, dims: Dims) -> None:
        self._check_agent(self.agent, dims)
        _expect("msg", "msg_dim", self.msg.shape[1], dims.msg_dim)


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
            _expect("msg", "msg_dim", self.msg.shape[1], dims.msg_dim)
        if dims.discrete is not None and dims.discrete != self.discrete:
            want = "(K,) int64 ids" if dims.discrete else "(K, A) float32 vectors"
            raise ShapeError(f"actions must be {want}, got {self.action.dtype} {self.action.shape}", "action")
        if dims.action_dim is None:
            return
        if self.discrete:
            if self.action.size:
                lo, hi = _min_max(self.action)
                if lo < 0 or hi >= dims.action_dim:
                    raise RangeError(f"action ids must be in [0, {dims.action_dim})", "action")
        else:
            _expect("action", "action vector length", self.action.shape[1], dims.action_dim)


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
            raise _err("checksum", "sha256", "sha256 of blob does not match (corrupted or truncated weights)")
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


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.TYPE: cls
    for cls in (LocalObs, GlobalState, CentralMsg, Action, ExperienceChunk, Weights, Control, Heartbeat)
}


def json_schemas() -> dict[str, Any]:
    """JSON Schema (validation side) of every message type, keyed by type tag."""
    return {
        "schema_version": SCHEMA_VERSION,
        "messages": {tag: cls.model_json_schema() for tag, cls in MESSAGE_TYPES.items()},
    }


# --------------------------------------------------------------------------------------------
# Fast path
# --------------------------------------------------------------------------------------------
#
# Why: pydantic validating one K=32 message of the control loop costs several times what the
# bytes do (core schema walk, one Python validator call per array, np.unique, model validators;
# `hammer bench codec` prints both paths), and every vector step builds and decodes a dozen of them. The hot types below get a second, hand-written validator
# that accepts a message only when every check of the pydantic model passes (dtypes, ranks,
# shapes, byte counts, bool bytes, finiteness, ranges, unique env indices, strict ints and
# strings, no unknown or missing fields). It never raises its own errors: whenever it declines,
# the caller runs the pydantic model, which either accepts (then its result is used) or raises
# the reference error. So errors are exactly pydantic's by construction, and the only way the
# two can differ is the fast path accepting what pydantic rejects; tests/test_protocol_fastpath.py
# checks they agree on a corpus of good and deliberately broken messages plus fuzzing.
#
# It takes the same inputs as the models: wire maps straight from msgpack (decode) and numpy
# arrays / Python values (building a message), and it reads dtypes, ranks and defaults from the
# model fields, so the schema itself is still declared once, above.


class _Decline(Exception):
    """The fast path does not vouch for this input; pydantic decides."""


_setattr = object.__setattr__
_FAST_OK = sys.byteorder == "little"  # wire arrays are little-endian: decode them without a swap
try:  # the C function behind np.count_nonzero, without its Python dispatch wrapper (numpy >= 2)
    from numpy._core.multiarray import count_nonzero as _count_nonzero
except ImportError:  # pragma: no cover - numpy 1.x
    _count_nonzero = np.count_nonzero
# env_idx is almost always 0..K-1: comparing its bytes with these proves "unique and >= 0" at once.
_ARANGE_BYTES = np.arange(4096, dtype="<i8").tobytes()
_RUN_MATCH = re.compile(NAME_RE.pattern.removeprefix("^").removesuffix("$")).fullmatch


def _set_state(obj: BaseModel, values: dict[str, Any], fields_set: set[str]) -> None:
    """What pydantic's `model_construct` sets on a model (extra="forbid", no private attributes)."""
    _setattr(obj, "__dict__", values)
    _setattr(obj, "__pydantic_fields_set__", fields_set)
    _setattr(obj, "__pydantic_extra__", None)
    _setattr(obj, "__pydantic_private__", None)


def _nonneg_int(v: Any) -> int:
    if type(v) is not int or v < 0:
        raise _Decline
    return v


def _version(v: Any) -> int:
    if type(v) is not int or v != SCHEMA_VERSION:
        raise _Decline
    return v


def _run(v: Any) -> str:
    if type(v) is not str or (v and _RUN_MATCH(v) is None):
        raise _Decline
    return v


def _sender(v: Any) -> str:
    if type(v) is not str or len(v) > 128:
        raise _Decline
    return v


def _array_check(spec: _ArrayField, optional: bool) -> Callable[[Any], np.ndarray | None]:
    """The checks of `_ArrayField.validate` (plus _array_from_wire) for one field."""
    names = frozenset(spec.dtypes)
    by_dtype = {WIRE_DTYPES[n]: n for n in spec.dtypes}  # little-endian = native here
    ndims = frozenset(spec.ndims if spec.ndims is not None else range(MAX_NDIM + 1))

    def check(v: Any) -> np.ndarray | None:
        if type(v) is np.ndarray:
            if v.dtype not in by_dtype or v.ndim not in ndims:
                raise _Decline
            a = v
        elif type(v) is dict:
            name, shape, data = v.get("dtype"), v.get("shape"), v.get("data")
            if (len(v) != 3 or type(name) is not str or name not in names or type(shape) is not list
                    or len(shape) not in ndims or type(data) is not bytes):
                raise _Decline
            count = 1
            for n in shape:
                if type(n) is not int or n < 0:
                    raise _Decline
                count *= n
            dtype = WIRE_DTYPES[name]
            if count * dtype.itemsize != len(data):
                raise _Decline
            if name == "bool" and data.translate(None, b"\x00\x01"):  # any byte other than 0 / 1 left
                raise _Decline
            # A copy into a bytearray: writable, native (little-endian) and does not pin the payload.
            a = np.frombuffer(bytearray(data), dtype).reshape(shape)
        elif v is None and optional:
            return None
        else:
            raise _Decline
        if a.dtype.kind == "f" and _count_nonzero(np.isfinite(a)) != a.size:
            raise _Decline
        return a

    return check


def _env_idx(check: Callable[[Any], np.ndarray | None]) -> Callable[[Any], np.ndarray]:
    def env_idx(v: Any) -> np.ndarray:
        a = check(v)
        if a.size and not _ARANGE_BYTES.startswith(a.tobytes()):  # int64 native = little-endian here
            idx = a.tolist()
            if min(idx) < 0 or len(set(idx)) != len(idx):
                raise _Decline
        return a

    return env_idx


def _field_check(cls: type[Message], name: str, info: Any) -> Callable[[Any], Any]:
    """The fast check of one model field, from its declaration where it is an array."""
    if name == "type":
        tag = cls.TYPE

        def type_tag(v: Any) -> str:
            if type(v) is not str or v != tag:
                raise _Decline
            return v

        return type_tag
    scalar = {"v": _version, "run": _run, "sender": _sender, "step": _nonneg_int, "ts": _nonneg_int,
              "seq": _nonneg_int, "agent": _nonneg_int, "policy_version": _nonneg_int}
    if name in scalar:
        return scalar[name]
    for meta in info.metadata:
        if isinstance(meta, _ArrayField):
            check = _array_check(meta, optional=False)
            return _env_idx(check) if name == "env_idx" else check
    args = typing.get_args(info.annotation)
    if type(None) in args:
        for arg in args:
            for meta in getattr(arg, "__metadata__", ()):
                if isinstance(meta, _ArrayField):
                    return _array_check(meta, optional=True)
    raise TypeError(f"{cls.__name__}.{name}: no fast-path check for this field; add one in protocol/schemas.py")


def _local_obs_shapes(v: dict, k: int) -> None:
    if v["obs"].shape[0] != k or v["active"].shape[0] != k:
        raise _Decline


def _global_state_shapes(v: dict, k: int) -> None:
    obs, prev = v["obs"].shape, v["prev_actions"].shape
    if obs[0] != k or prev[0] != k or prev[1] != obs[1] or v["active"].shape != obs[:2]:
        raise _Decline


def _central_msg_shapes(v: dict, k: int) -> None:
    m = v["msg"]
    if m.shape[0] != k or _count_nonzero(np.abs(m) <= 1.0) != m.size:
        raise _Decline


def _action_shapes(v: dict, k: int) -> str | None:
    a = v["action"]
    if a.shape[0] != k or a.ndim != (1 if a.dtype == np.int64 else 2):
        raise _Decline
    for name in ("fallback", "msg"):
        x = v[name]
        if x is not None and x.shape[0] != k:
            raise _Decline
    if v["fallback"] is None:
        v["fallback"] = np.zeros(k, dtype=bool)
        return "fallback"
    return None


def _fast_validator(cls: type[Message], shapes: Callable[[dict, int], str | None]) -> Callable:
    """validate(data) -> (field values, fields set) exactly as pydantic would produce them, or raise."""
    fields = []
    for name, info in cls.model_fields.items():
        if info.default_factory is not None:
            default, factory = None, info.default_factory
        else:
            default, factory = (_Decline if info.is_required() else info.default), None
        fields.append((name, _field_check(cls, name, info), default, factory))
    known = frozenset(cls.model_fields)

    def validate(data: dict) -> tuple[dict[str, Any], set[str]]:
        if not _FAST_OK or not known.issuperset(data):  # unknown field (or a non-str key)
            raise _Decline
        values = {}
        for name, check, default, factory in fields:
            if name in data:
                values[name] = check(data[name])
            elif factory is not None:
                values[name] = factory()
            elif default is _Decline:  # required and missing
                raise _Decline
            else:
                values[name] = default
        fields_set = set(data)
        added = shapes(values, values["env_idx"].shape[0])
        if added is not None:  # the pydantic model validator assigned it, which marks it set
            fields_set.add(added)
        return values, fields_set

    return validate


_FAST: dict[type[Message], Callable[[dict], tuple[dict[str, Any], set[str]]]] = {
    cls: _fast_validator(cls, shapes)
    for cls, shapes in ((LocalObs, _local_obs_shapes), (GlobalState, _global_state_shapes),
                        (CentralMsg, _central_msg_shapes), (Action, _action_shapes))
}
FAST_TYPES = frozenset(_FAST)


def _fast_state(cls: type[Message], data: dict) -> tuple[dict[str, Any], set[str]] | None:
    """(field values, fields set) of `data` by the fast path, or None when it declines or `cls`
    has none: then pydantic must validate `data`."""
    fast = _FAST.get(cls)
    if fast is None:
        return None
    try:
        return fast(data)
    except Exception:  # noqa: BLE001 - any failure of the fast path means "let pydantic decide"
        return None


def fast_from_wire(cls: type[Message], d: dict) -> Message | None:
    """The message of wire map `d` built by the fast path, or None (then validate with pydantic)."""
    state = _fast_state(cls, d)
    if state is None:
        return None
    msg = cls.__new__(cls)
    _set_state(msg, *state)
    return msg
