"""Every message the hammer roles exchange, defined once, as msgspec Structs.

Why msgspec: the edge agent pays for every import, and the wire path does not need pydantic
(docs/deploy.md "Footprint"); the typed decode of a Struct checks every scalar in C in the same pass that parses the
bytes, so a message is decoded and validated once (`hammer bench codec` prints the cost). There is one definition per message: the Struct
says the wire layout and the scalar checks (msgspec applies them while decoding: strict ints,
bounds, lengths, patterns, literals, no unknown or missing fields, no ext types), and its
`__post_init__` makes the checks msgspec cannot (arrays: dtype, rank, byte count, finiteness,
shapes that must agree, the message range) with `protocol.fields.ArraySpec`. msgspec runs
`__post_init__` both when code builds a message (`LocalObs(agent=0, obs=..., active=...)`) and when
it decodes one, so a NaN or a wrong dtype is refused at the sender as well as at the receiver.
`hammer protocol schema` is generated from these Structs (`json_schemas`).

Why batched: encoding and decoding a message has a fixed Python cost far above that of its bytes
(`hammer bench codec` prints it), so one message carries all K env copies of one vector step
(arrays have a leading K axis), never one per copy.

The wire form is compact (docs/wire-format.md): a msgpack array, fields by
position (`array_like`: no field names on the wire), first the type tag (a small int), then the
header `v, step, env_idx, sender`, then the type's fields; optional fields left at their default
at the end are not sent. The run id is the key's (`hammer/<run>/...`: a subscription covers only
its own run), a receiver dates a message by its arrival (no send time), and the sender is empty
where the key implies it (protocol/binding.py fills it in from the key; any other sender is
checked against the key). `env_idx` goes as the int K when it is 0..K-1 (nearly always), else as
a list of ints (msgpack ints are as narrow as their values).

Array conventions (K = env copies in this message, N = agents, D = obs dim, M = message length,
A = action vector length):
  LocalObs     obs (K,D) float32, active (K,) bool
  GlobalState  obs (K,N,D) float32, prev_actions (K,N,A) float32, active (K,N) bool
  CentralMsg   msg (K,M) float32 in [-1,1]
  SiteState    cols (K,C) float32 (C = the central-only columns of an observation row)
  Action       action (K,) int64 (discrete) or (K,A) float32 (continuous), fallback (K,) bool, msg (K,M) float32
  ExperienceChunk  the arrays of protocol/rollout_layout.py
"""

from __future__ import annotations

import hashlib
import math
from array import array
from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Literal

import msgspec
from hammer.protocol import fields as _fields
from hammer.protocol.dims import Dims, expect, min_max
from hammer.protocol.errors import ChecksumError, FieldError, NonFiniteError, RangeError, ShapeError
from hammer.protocol.fields import (
    ARRAY_DTYPES,
    ARRAY_NAME_PATTERN,
    DEFAULT_MAX_BYTES,
    HEADER_BYTES,
    NAME_RE,
    ArraySpec,
    MiB,
    WireArray,
    empty_idx,
    numpy_loaded,
)
from msgspec import Meta

if TYPE_CHECKING:
    from hammer.protocol.rollout_layout import RolloutLayout

# numpy where this process has loaded it, bound by `numpy_loaded(globals())`: every role but the lite
# edge agent, which keeps its arrays as `WireArray`s checked in pure Python (protocol/fields.py).
np: Any = None

# Any change of a message's layout raises it: a peer of another version is refused by name, never misread
# (docs/wire-format.md says what each version changed).
SCHEMA_VERSION = 7

# Scalar wire types (msgspec checks them while decoding).
NonNegInt = Annotated[int, Meta(ge=0)]  # no upper bound: the roles bound steps and versions (runtime/bounds.py)
Name = Annotated[str, Meta(pattern=NAME_RE.pattern)]
ArrayName = Annotated[str, Meta(pattern=ARRAY_NAME_PATTERN)]
Scalar = None | bool | int | float | Annotated[str, Meta(max_length=256)]
MAX_K = (1 << 16) - 1  # env copies in one message (env_idx sent as the count K)
_ENV_IDX_WIRE = Annotated[int, Meta(ge=0, le=MAX_K)] | list[Annotated[int, Meta(ge=0, le=(1 << 63) - 1)]]
_WIRE_ARRAY = tuple[int, list[int], bytes]

# Array fields: what each holds (and narrower wire dtypes it accepts).
F32 = ("float32",)
_HALF = (("float16", "float32"),)  # opt-in compact observations and messages: float16 on the wire, float32 read
OBS2 = ArraySpec(F32, (2,), _HALF)
OBS3 = ArraySpec(F32, (3,), _HALF)
MSG2 = ArraySpec(F32, (2,), _HALF)
BOOL1 = ArraySpec(("bool",), (1,))
BOOL2 = ArraySpec(("bool",), (2,))
# (K,) int64 ids (uint8 on the wire when every id fits) or (K, A) float32 vectors.
ACTION = ArraySpec(("int64", "float32"), (1, 2), (("uint8", "int64"),))
ANY_ARRAY = ArraySpec(ARRAY_DTYPES)


def Arr(spec: ArraySpec, description: str) -> Any:
    """The wire type of an array field, documented from its spec (for `hammer protocol schema`)."""
    schema = spec.json_schema()
    return Annotated[_WIRE_ARRAY, Meta(description=f"{description}; {schema.pop('description')}",
                                        extra_json_schema={_ARRAY_ITEMS: schema["prefixItems"]})]


_ARRAY_ITEMS = "x-array-items"  # set by `Arr`, put in place of msgspec's generic items by `json_schemas`


def _array_items(node: Any) -> Any:
    """The schema tree with each array field's items (dtype codes, shape, data) as its spec says."""
    if isinstance(node, dict):
        node = {k: _array_items(v) for k, v in node.items()}
        if _ARRAY_ITEMS in node:
            node["prefixItems"] = node.pop(_ARRAY_ITEMS)
        return node
    if isinstance(node, list):
        return [_array_items(v) for v in node]
    return node


# Messages
# --------------------------------------------------------------------------------------------

# env_idx is almost always 0..K-1: comparing its bytes with these proves "unique and >= 0" at once.
_ARANGE_BYTES = array("q", range(4096)).tobytes()


def _is_range(a: Any) -> bool:
    """Whether int64 array `a` is 0..K-1."""
    k = a.shape[0]
    if k <= 4096:
        return _ARANGE_BYTES.startswith(a.tobytes())
    if type(a) is WireArray:
        return a.tolist() == list(range(k))
    return bool((a == np.arange(k)).all())


def _bools(shape: tuple[int, ...], value: bool) -> Any:
    """A bool array of `shape`, every element `value` (a field's default)."""
    if np is None and not numpy_loaded(globals()):
        return WireArray("bool", shape, (b"\x01" if value else b"\x00") * math.prod(shape))
    return np.ones(shape, dtype=bool) if value else np.zeros(shape, dtype=bool)


def _env_idx(v: Any) -> Any:
    """env_idx from code (an int64 ndarray) or from the wire (K, or a list of indices): unique, >= 0."""
    t = type(v)
    if t is int:  # 0..K-1 (msgspec bounded K)
        if not 0 <= v <= MAX_K:
            raise RangeError(f"K must be in [0, {MAX_K}]", "env_idx")
        if np is None and not numpy_loaded(globals()):
            return WireArray("int64", (v,), _ARANGE_BYTES[:8 * v] if v <= 4096 else array("q", range(v)).tobytes())
        return np.arange(v, dtype=np.int64)
    if np is None and not numpy_loaded(globals()):
        return _env_idx_lite(v, t)
    if t is np.ndarray:
        if v.dtype != np.int64:
            raise FieldError(f"env_idx must be int64, got {v.dtype}", "env_idx")
        if v.ndim != 1:
            raise ShapeError(f"env_idx must be (K,), got shape {v.shape}", "env_idx")
        a = v
    elif t is list:
        a = np.array(v, dtype=np.int64) if v else empty_idx()
    elif t is WireArray and v.dtype == "int64" and v.ndim == 1:  # built before numpy was loaded
        a = np.array(v.tolist(), dtype=np.int64)
    else:
        raise FieldError(f"env_idx must be an int or a list of ints, got {t.__name__}", "env_idx")
    if a.size and not _is_range(a):
        idx = a.tolist()  # a Python set beats np.unique at K up to a few thousand
        if min(idx) < 0:
            raise RangeError("env indices must be >= 0", "env_idx")
        if len(set(idx)) != len(idx):
            raise ShapeError("env indices must be unique", "env_idx")
    return a


def _env_idx_lite(v: Any, t: type) -> WireArray:
    """`_env_idx` without numpy (v is not an int): the same checks, in the same order."""
    if t is WireArray:
        if v.dtype != "int64":
            raise FieldError(f"env_idx must be int64, got {v.dtype}", "env_idx")
        if v.ndim != 1:
            raise ShapeError(f"env_idx must be (K,), got shape {v.shape}", "env_idx")
        a = v
    elif t is list:
        a = WireArray.of("int64", (len(v),), v) if v else empty_idx()
    else:
        raise FieldError(f"env_idx must be an int or a list of ints, got {t.__name__}", "env_idx")
    if a.size and not _is_range(a):
        idx = a.tolist()
        if min(idx) < 0:
            raise RangeError("env indices must be >= 0", "env_idx")
        if len(set(idx)) != len(idx):
            raise ShapeError("env indices must be unique", "env_idx")
    return a


def env_idx_to_wire(a: Any) -> int | list[int]:
    """What env_idx puts on the wire: K when it is 0..K-1, else the list of indices."""
    if a.shape[0] <= MAX_K and _is_range(a):
        return a.shape[0]
    return a.tolist()


class Message(msgspec.Struct, array_like=True, forbid_unknown_fields=True):
    """Common header of every message.

    `sender` is stamped by `HammerSession.publish` (empty where the key implies it); code that builds
    a message only sets `step` and `env_idx` (plus the payload).
    """

    TYPE: ClassVar[str] = ""
    TAG: ClassVar[int] = 0
    MAX_BYTES: ClassVar[int] = DEFAULT_MAX_BYTES
    # Array fields: name -> (spec, wire nil means: None, or a fill "ones"/"zeros" of shape (K,)).
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {}

    v: Annotated[int, Meta(description="schema version (SCHEMA_VERSION)")] = SCHEMA_VERSION
    step: Annotated[NonNegInt, Meta(description="vector step")] = 0
    env_idx: Annotated[_ENV_IDX_WIRE, Meta(
        description="the env copies this message carries: K (= 0..K-1), or the list of their indices (unique, >= 0)"
    )] = msgspec.field(default_factory=empty_idx)
    sender: Annotated[str, Meta(max_length=128, description="sender name; empty: the one its key implies")] = ""

    @property
    def type(self) -> str:
        """The type tag's name (`local_obs`, ...)."""
        return self.TYPE

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
            raise ShapeError(f"shape {a.shape} disagrees with the message, expected {want} (K={self.k} from env_idx)",
                             field)

    def __post_init__(self) -> None:
        self.env_idx = _env_idx(self.env_idx)

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


class LocalObs(Message, tag=1, kw_only=True):
    """Env host -> local agent `agent`: its observation in each env copy."""

    TYPE: ClassVar[str] = "local_obs"
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {"obs": OBS2, "active": BOOL1, "msg": MSG2}
    agent: NonNegInt
    obs: Arr(OBS2, "(K, D) float32")
    policy_version: Annotated[NonNegInt, Meta(
        description="policy version the agent must act with (on-policy sync)")] = 0
    # Said by the env host, the one that records (training, a trace), so that an agent needs no setting
    # of its own to know it: an edge agent joins a served run with nothing but a bundle and a run id.
    echo: Annotated[bool, Meta(description="send the message acted on back in the action's `msg`: the env host "
                                           "records it (training, or a trace)")] = False
    active: Arr(BOOL1, "(K,) bool: the agent is present in that copy; nil: in every copy") | None = None
    # A fleet's world sends the central agent's message for this observation in it: one message down
    # per robot per tick instead of two, each with its own packet (docs/fleet.md). Never in training.
    msg: Arr(MSG2, "(K, M) float32 in [-1, 1]: the central message for this observation (a fleet's world); "
                   "nil: none came with it") | None = None

    @classmethod
    def _array_bytes(cls, dims: Dims) -> int | None:
        if dims.num_envs is None or dims.obs_dim is None:
            return None
        return dims.num_envs * (8 + 4 * dims.obs_dim + 1 + 4 * (dims.msg_dim or 0))  # env_idx, obs, active, msg

    def __post_init__(self) -> None:
        self.env_idx = idx = _env_idx(self.env_idx)
        k = idx.shape[0]
        self.obs = OBS2.take(self.obs, "obs")
        self._need("obs", self.obs, (k, None))
        if self.active is None:
            self.active = _bools((k,), True)
        else:
            self.active = BOOL1.take(self.active, "active")
            self._need("active", self.active, (k,))
        if self.msg is not None:
            self.msg = MSG2.take(self.msg, "msg")
            self._need("msg", self.msg, (k, None))
            if not _in_unit_range(self.msg):
                raise RangeError("message values must lie in [-1, 1]", "msg")

    def _check_dims(self, dims: Dims) -> None:
        self._check_agent(self.agent, dims)
        expect("obs", "obs_dim", self.obs.shape[1], dims.obs_dim)
        if self.msg is not None:
            expect("msg", "msg_dim", self.msg.shape[1], dims.msg_dim)


class GlobalState(Message, tag=2, kw_only=True):
    """Env host -> central agent: all observations and every agent's previous action."""

    TYPE: ClassVar[str] = "global_state"
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {"obs": OBS3, "prev_actions": OBS3, "active": BOOL2}
    obs: Arr(OBS3, "(K, N, D) float32")
    prev_actions: Arr(OBS3, "(K, N, A) float32: continuous actions, or for discrete actions a one-hot "
                            "(A = n_actions) or the action id as a float (A = 1); zeros on the first step")
    policy_version: Annotated[NonNegInt, Meta(description="policy version the central agent must use")] = 0
    active: Arr(BOOL2, "(K, N) bool; nil: every agent in every copy") | None = None

    @classmethod
    def _array_bytes(cls, dims: Dims) -> int | None:
        k, n, d, a = dims.num_envs, dims.n_agents, dims.obs_dim, dims.action_dim
        if k is None or n is None or d is None or a is None:
            return None
        return k * (8 + n * (4 * d + 4 * max(a, 1) + 1))  # env_idx, obs, prev_actions, active

    def __post_init__(self) -> None:
        self.env_idx = idx = _env_idx(self.env_idx)
        k = idx.shape[0]
        self.obs = OBS3.take(self.obs, "obs")
        n = self.obs.shape[1]
        self._need("obs", self.obs, (k, n, None))
        self.prev_actions = OBS3.take(self.prev_actions, "prev_actions")
        self._need("prev_actions", self.prev_actions, (k, n, None))
        if self.active is None:
            self.active = _bools((k, n), True)
        else:
            self.active = BOOL2.take(self.active, "active")
            self._need("active", self.active, (k, n))

    def _check_dims(self, dims: Dims) -> None:
        expect("obs", "n_agents", self.obs.shape[1], dims.n_agents)
        expect("obs", "obs_dim", self.obs.shape[2], dims.obs_dim)
        a = self.prev_actions.shape[2]
        if dims.action_dim is not None and dims.discrete is not None:
            ok = a in (1, dims.action_dim) if dims.discrete else a == dims.action_dim
            if not ok:
                raise ShapeError(f"last dim {a} does not fit action_dim {dims.action_dim}", "prev_actions")


def _in_unit_range(m: Any) -> bool:
    if type(m) is WireArray:
        return all(-1.0 <= x <= 1.0 for x in m.tolist(flat=True))
    return _fields.count_nonzero(np.abs(m) <= 1.0) == m.size  # NaN is refused before: finiteness


class CentralMsg(Message, tag=3, kw_only=True):
    """Central agent -> local agent `agent`: its message vector in each env copy."""

    TYPE: ClassVar[str] = "central_msg"
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {"msg": MSG2}
    agent: NonNegInt
    msg: Arr(MSG2, "(K, M) float32 in [-1, 1]")
    policy_version: NonNegInt = 0

    @classmethod
    def _array_bytes(cls, dims: Dims) -> int | None:
        if dims.num_envs is None or dims.msg_dim is None:
            return None
        return dims.num_envs * (8 + 4 * dims.msg_dim)  # env_idx, msg

    def __post_init__(self) -> None:
        self.env_idx = idx = _env_idx(self.env_idx)
        self.msg = MSG2.take(self.msg, "msg")
        self._need("msg", self.msg, (idx.shape[0], None))
        if not _in_unit_range(self.msg):
            raise RangeError("message values must lie in [-1, 1]", "msg")

    def _check_dims(self, dims: Dims) -> None:
        self._check_agent(self.agent, dims)
        expect("msg", "msg_dim", self.msg.shape[1], dims.msg_dim)


def _is_ids(a: Any) -> bool:
    """Whether an action array holds discrete ids (int64), not continuous vectors."""
    if type(a) is not WireArray and np is not None:
        return a.dtype == np.int64
    if type(a) is WireArray:
        return a.dtype == "int64"
    numpy_loaded(globals())  # an ndarray passed in before any message was built here
    return a.dtype == np.int64


def _take_action(msg: Message, value: Any) -> Any:
    a = ACTION.take(value, "action")
    msg._need("action", a, (msg.k,) if _is_ids(a) else (msg.k, None))
    return a


class Action(Message, tag=4, kw_only=True):
    """Local agent `agent` -> env host: its action in each env copy.

    `msg` echoes the message the agent acted on back to the env host, which records it in the
    rollout (learning/rollout.py: the learner trains on what the agent saw). Only training needs it:
    an agent serving (mode eval) leaves it out, and an env host that trains declares
    `Dims(echo=True)`, so an action without it is refused there (`field`), not recorded as zeros."""

    TYPE: ClassVar[str] = "action"
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {"action": ACTION, "fallback": BOOL1, "msg": MSG2}
    agent: NonNegInt
    action: Arr(ACTION, "(K,) int64 action ids (uint8 on the wire when every id fits), "
                        "or (K, A) float32 continuous actions")
    policy_version: Annotated[NonNegInt, Meta(description="the version that acted")] = 0
    fallback: Arr(BOOL1, "(K,) the central message was late and a fallback was used; nil: none was") | None = None
    msg: Arr(MSG2, "(K, M) float32: the message the agent acted on (received or fallback), for the "
                   "rollout; nil when the variant has no messages or the agent is not training") | None = None

    @classmethod
    def _array_bytes(cls, dims: Dims) -> int | None:
        k, a, m = dims.num_envs, dims.action_dim, dims.msg_dim
        if k is None or a is None or m is None or dims.discrete is None:
            return None
        return k * (8 + (8 if dims.discrete else 4 * a) + 1 + 4 * m)  # env_idx, action, fallback, msg

    def __post_init__(self) -> None:
        self.env_idx = idx = _env_idx(self.env_idx)
        k = idx.shape[0]
        self.action = _take_action(self, self.action)
        if self.fallback is None:
            self.fallback = _bools((k,), False)
        else:
            self.fallback = BOOL1.take(self.fallback, "fallback")
            self._need("fallback", self.fallback, (k,))
        if self.msg is not None:
            self.msg = MSG2.take(self.msg, "msg")
            self._need("msg", self.msg, (k, None))

    @property
    def discrete(self) -> bool:
        return _is_ids(self.action)

    def _check_dims(self, dims: Dims) -> None:
        self._check_agent(self.agent, dims)
        if self.msg is not None:
            expect("msg", "msg_dim", self.msg.shape[1], dims.msg_dim)
        elif dims.echo and dims.msg_dim:
            raise FieldError("missing: a training env host records the message each action used", "msg")
        check_actions(self.action, dims)


def check_actions(action: Any, dims: Dims) -> None:
    """An `action` field against declared dims (an action's, an uplink's): ids or vectors as declared,
    ids within the action count, vectors of the declared length."""
    discrete = _is_ids(action)
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


_PLAIN = frozenset({int, float, bool, str, type(None)})


def _scalars(values: Any, field: str) -> dict:
    """A map of wire scalars, checked: finite floats; numpy scalars (a counter summed with numpy)
    become Python ones, which is what msgpack carries. Anything else is refused at the sender."""
    if type(values) is not dict:
        raise FieldError(f"must be a map, got {type(values).__name__}", field)
    out = values
    for name, x in values.items():
        t = type(x)
        if t not in _PLAIN:
            lib = np if np is not None or numpy_loaded(globals()) else None  # no numpy: no numpy scalars
            if isinstance(x, bool) or (lib is not None and isinstance(x, lib.bool_)):
                x = bool(x)
            elif isinstance(x, int) or (lib is not None and isinstance(x, lib.integer)):
                x = int(x)
            elif isinstance(x, float) or (lib is not None and isinstance(x, lib.floating)):
                x = float(x)
            else:
                raise FieldError(f"{t.__name__} is not a wire scalar", f"{field}.{name}")
            if out is values:
                out = dict(values)
            out[name] = x
        if type(x) is float and not math.isfinite(x):
            raise NonFiniteError("holds NaN or inf", f"{field}.{name}")
    return out


class ExperienceChunk(Message, tag=5, kw_only=True):
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
    RECORD_ROLE: ClassVar[str] = "central"
    role: Name
    policy_version: NonNegInt
    arrays: Annotated[dict[ArrayName, Arr(ANY_ARRAY, "an array of the rollout layout")], Meta(max_length=64)]
    meta: Annotated[dict[ArrayName, Scalar], Meta(max_length=64)] = msgspec.field(default_factory=dict)

    @classmethod
    def cap_for(cls, layout: RolloutLayout) -> int:
        """The size cap of one run's rollout chunk: the default cap, or the chunk's arrays plus 1 MiB
        of framing when they are larger (cn at large N: docs/scale.md). Sender and learner
        both derive it from the run's layout, so a payload beyond it is still refused on arrival."""
        return max(cls.MAX_BYTES, layout.chunk_nbytes() + MiB)

    def __post_init__(self) -> None:
        self.env_idx = _env_idx(self.env_idx)
        if type(self.arrays) is not dict or len(self.arrays) > 64:
            raise FieldError("must be a map of at most 64 named arrays", "arrays")
        self.arrays = {name: ANY_ARRAY.take(a, f"arrays.{name}") for name, a in self.arrays.items()}
        self.meta = _scalars(self.meta, "meta")

    def _check_dims(self, dims: Dims) -> None:
        layout = dims.rollout_layout()
        if layout is None:
            return
        if self.role == self.RECORD_ROLE:
            layout.check_record(self.arrays, k=self.k)
        else:
            layout.check_chunk(self.arrays)


class Weights(Message, tag=6, kw_only=True):
    """A learner -> actors: a policy version as a safetensors blob with its sha256."""

    TYPE: ClassVar[str] = "weights"
    MAX_BYTES: ClassVar[int] = 256 * MiB
    role: Name
    version: NonNegInt
    blob: bytes
    sha256: Annotated[str, Meta(pattern=r"^[0-9a-f]{64}$")]
    format: Literal["safetensors"] = "safetensors"

    def __post_init__(self) -> None:
        self.env_idx = _env_idx(self.env_idx)
        if type(self.blob) is not bytes:
            raise FieldError(f"must be bytes, got {type(self.blob).__name__}", "blob")
        if hashlib.sha256(self.blob).hexdigest() != self.sha256:
            raise ChecksumError("sha256 of blob does not match (corrupted or truncated weights)", "sha256")

    @classmethod
    def from_blob(cls, role: str, version: int, blob: bytes, **header: Any) -> Weights:
        """Build a Weights message computing the sha256 of `blob`."""
        return cls(role=role, version=version, blob=blob, sha256=hashlib.sha256(blob).hexdigest(), **header)


# A pushed version, pulled in chunks (WeightsAnnounce, WeightsChunk): the bounds of what an announcement may declare.
MIN_CHUNK_BYTES = 64
MAX_CHUNK_BYTES = 64 * 1024
MAX_CHUNKS = 1 << 16
CHUNK_DIGEST_BYTES = 8  # each chunk's digest in the announcement: the first 8 bytes of its sha256


def chunk_digest(data: bytes) -> bytes:
    """What an announcement lists for one chunk (the whole blob's sha256 is checked as well)."""
    return hashlib.sha256(data).digest()[:CHUNK_DIGEST_BYTES]


class WeightsAnnounce(Message, tag=10, kw_only=True):
    """Policy server -> local agents: a pushed policy version exists; each agent pulls it in chunks.

    Why not the weights themselves: on a thin link a 35 kB Weights message sits in the kernel's
    queue ahead of the steps' traffic for a second (docs/deploy.md, "A push on a thin link"). The
    announcement says what to fetch and how to check it: the blob's size and sha256, the chunk
    size, and each chunk's digest (`chunk_digest`, 8 bytes per chunk), so a bad chunk is refused
    on arrival, not only once the whole blob fails its sha256."""

    TYPE: ClassVar[str] = "weights_announce"
    MAX_BYTES: ClassVar[int] = HEADER_BYTES + MAX_CHUNKS * CHUNK_DIGEST_BYTES
    role: Name
    version: NonNegInt
    size: Annotated[int, Meta(ge=1, le=256 * MiB, description="bytes of the whole blob")]
    sha256: Annotated[str, Meta(pattern=r"^[0-9a-f]{64}$")]
    chunk_bytes: Annotated[int, Meta(ge=MIN_CHUNK_BYTES, le=MAX_CHUNK_BYTES,
                                     description="bytes of every chunk but the last")]
    digests: Annotated[bytes, Meta(max_length=MAX_CHUNKS * CHUNK_DIGEST_BYTES, description=(
        "the chunks' digests in order, 8 bytes each: the first 8 bytes of each chunk's sha256"))]
    format: Literal["safetensors"] = "safetensors"

    def __post_init__(self) -> None:
        self.env_idx = _env_idx(self.env_idx)
        if type(self.digests) is not bytes:
            raise FieldError(f"must be bytes, got {type(self.digests).__name__}", "digests")
        n = -(-self.size // self.chunk_bytes)
        if n > MAX_CHUNKS:
            raise RangeError(f"{n} chunks of {self.chunk_bytes} B, over {MAX_CHUNKS}", "chunk_bytes")
        if len(self.digests) != n * CHUNK_DIGEST_BYTES:
            raise FieldError(f"{len(self.digests)} bytes for {n} chunks of {CHUNK_DIGEST_BYTES}", "digests")

    @property
    def chunks(self) -> int:
        return len(self.digests) // CHUNK_DIGEST_BYTES

    def digest(self, index: int) -> bytes:
        return self.digests[index * CHUNK_DIGEST_BYTES:(index + 1) * CHUNK_DIGEST_BYTES]

    def chunk_size(self, index: int) -> int:
        """The bytes chunk `index` must hold (the last one: the rest)."""
        return min(self.chunk_bytes, self.size - index * self.chunk_bytes)

    @classmethod
    def of(cls, role: str, version: int, blob: bytes, chunk_bytes: int, **header: Any) -> WeightsAnnounce:
        """The announcement of `blob` cut into chunks of `chunk_bytes`."""
        digests = b"".join(chunk_digest(blob[i:i + chunk_bytes]) for i in range(0, len(blob), chunk_bytes))
        return cls(role=role, version=version, size=len(blob), sha256=hashlib.sha256(blob).hexdigest(),
                   chunk_bytes=chunk_bytes, digests=digests, **header)


class WeightsChunk(Message, tag=11, kw_only=True):
    """Policy server -> one local agent, the reply to its query `learn/<net>/chunk?v=<version>&i=<index>`:
    bytes [index * chunk_bytes, ...) of the announced version's blob (WeightsAnnounce)."""

    TYPE: ClassVar[str] = "weights_chunk"
    MAX_BYTES: ClassVar[int] = HEADER_BYTES + MAX_CHUNK_BYTES
    role: Name
    version: NonNegInt
    index: Annotated[int, Meta(ge=0, lt=MAX_CHUNKS)]
    data: Annotated[bytes, Meta(min_length=1, max_length=MAX_CHUNK_BYTES)]

    def __post_init__(self) -> None:
        self.env_idx = _env_idx(self.env_idx)
        if type(self.data) is not bytes:
            raise FieldError(f"must be bytes, got {type(self.data).__name__}", "data")


class Control(Message, tag=7, kw_only=True):
    """Launcher -> roles: a command with small arguments. Only what something sends and something
    handles: `stop` (the launcher and the env host end a run)."""

    TYPE: ClassVar[str] = "control"
    command: Literal["stop"]
    target: Annotated[str, Meta(pattern=f"^\\*$|{NAME_RE.pattern}", description="role name, or * for every role")] = "*"
    args: Annotated[dict[ArrayName, Scalar], Meta(max_length=32)] = msgspec.field(default_factory=dict)

    def __post_init__(self) -> None:
        self.env_idx = _env_idx(self.env_idx)
        self.args = _scalars(self.args, "args")


HeartbeatStatus = Literal["starting", "ready", "running", "paused", "stopping", "stopped", "error"]


class Heartbeat(Message, tag=8, kw_only=True):
    """Any role -> launcher: alive, what it is doing, a few counters."""

    TYPE: ClassVar[str] = "heartbeat"
    role: Name
    pid: NonNegInt
    status: HeartbeatStatus
    counters: Annotated[dict[ArrayName, NonNegInt | Annotated[float, Meta(ge=0)]], Meta(
        max_length=64, description="totals since the process started: finite, >= 0, never falling for one role "
                                   "and pid (a receiver refuses a heartbeat whose counters fall)")] = msgspec.field(
        default_factory=dict)
    gauges: Annotated[dict[ArrayName, int | float], Meta(
        max_length=16, description="current values that may move either way (policy version, latency percentiles, "
                                   "a running metric)")] = msgspec.field(default_factory=dict)
    detail: Annotated[str, Meta(max_length=1024)] = ""

    def __post_init__(self) -> None:
        self.env_idx = _env_idx(self.env_idx)
        self.counters = _scalars(self.counters, "counters")
        self.gauges = _scalars(self.gauges, "gauges")


class Uplink(Message, tag=9, kw_only=True):
    """Robot `agent` -> central agent, in a fleet (docs/fleet.md): what the robot's own sensors saw
    and the action it took last, so the central agent can build its state without a simulator.
    The central agent dates it by arrival."""

    TYPE: ClassVar[str] = "uplink"
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {"obs": OBS2, "action": ACTION}
    agent: NonNegInt
    obs: Arr(OBS2, "(K, D) float32: the robot's observation")
    action: Arr(ACTION, "(K,) int64 ids or (K, A) float32: the robot's previous action (nil: none yet)") | None = None

    @classmethod
    def _array_bytes(cls, dims: Dims) -> int | None:
        k, d, a = dims.num_envs, dims.obs_dim, dims.action_dim
        if k is None or d is None or a is None or dims.discrete is None:
            return None
        return k * (8 + 4 * d + (8 if dims.discrete else 4 * a))  # env_idx, obs, action

    def __post_init__(self) -> None:
        self.env_idx = idx = _env_idx(self.env_idx)
        self.obs = OBS2.take(self.obs, "obs")
        self._need("obs", self.obs, (idx.shape[0], None))
        if self.action is not None:
            self.action = _take_action(self, self.action)

    def _check_dims(self, dims: Dims) -> None:
        self._check_agent(self.agent, dims)
        expect("obs", "obs_dim", self.obs.shape[1], dims.obs_dim)
        if self.action is not None:
            check_actions(self.action, dims)


class SiteState(Message, tag=12, kw_only=True):
    """Site -> a fleet's central agent (docs/fleet.md, "The site feed"): the part of the central
    agent's state that no robot observes (a warehouse's requested shelves and goal cells, from its
    management system), the columns [L, D) of every observation row. The central agent dates it by
    arrival, holds it for `site_hold_s`, then uses zeros (the silent rule)."""

    TYPE: ClassVar[str] = "site_state"
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {"cols": OBS2}
    cols: Arr(OBS2, "(K, C) float32: the central-only columns, as the env writes them (K = 1 in a fleet)")

    @classmethod
    def _array_bytes(cls, dims: Dims) -> int | None:
        if dims.num_envs is None or dims.site_dim is None:
            return None
        return dims.num_envs * (8 + 4 * dims.site_dim)  # env_idx, cols

    def __post_init__(self) -> None:
        self.env_idx = idx = _env_idx(self.env_idx)
        self.cols = OBS2.take(self.cols, "cols")
        self._need("cols", self.cols, (idx.shape[0], None))

    def _check_dims(self, dims: Dims) -> None:
        expect("cols", "site_dim", self.cols.shape[1], dims.site_dim)


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.TYPE: cls
    for cls in (LocalObs, GlobalState, CentralMsg, Action, ExperienceChunk, Weights, Control, Heartbeat, Uplink,
                WeightsAnnounce, WeightsChunk, SiteState)
}
for _cls in MESSAGE_TYPES.values():
    _cls.TAG = _cls.__struct_config__.tag
TAGS: dict[int, type[Message]] = {cls.TAG: cls for cls in MESSAGE_TYPES.values()}
numpy_loaded(globals())  # where numpy came first (every role but the lite edge agent): bound now


def fields_of(cls: type[Message]) -> tuple[str, ...]:
    """The fields of a message type in wire order (after the type tag)."""
    return cls.__struct_fields__


def json_schemas() -> dict[str, Any]:
    """JSON Schema of every message type's wire form (a msgpack array: the type tag, then the
    fields in order), keyed by type tag name; generated by msgspec from the Structs above."""
    classes = tuple(MESSAGE_TYPES.values())
    _refs, defs = msgspec.json.schema_components(classes, ref_template="#/$defs/{name}")
    messages = {}
    for cls in classes:
        schema = dict(defs[cls.__name__])
        schema["description"] = (cls.__doc__ or "").strip().split("\n\n")[0]
        schema["fields"] = ["type tag", *fields_of(cls)]
        schema["tag"] = cls.TAG
        messages[cls.TYPE] = schema
    others = {name: d for name, d in defs.items() if name not in {c.__name__ for c in classes}}
    return _array_items({"schema_version": SCHEMA_VERSION, "messages": messages, "$defs": others})
