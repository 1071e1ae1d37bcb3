"""A hand-written validator for the message types of the control loop.

Why: pydantic validating one K=32 message of the control loop costs several times what the
bytes do (core schema walk, one Python validator call per array, np.unique, model validators;
`hammer bench codec` prints both paths), and every vector step builds and decodes a dozen of them. The hot types below get a second, hand-written validator
that accepts a message only when every check of the pydantic model passes (dtypes, ranks,
shapes, byte counts, bool bytes, finiteness, ranges, unique env indices, strict ints and
strings, no unknown or missing fields). It never raises its own errors: whenever it declines,
the caller runs the pydantic model, which either accepts (then its result is used) or raises
the reference error. So errors are exactly pydantic's by construction, and the only way the
two can differ is the fast path accepting what pydantic rejects; tests/test_protocol_fastpath.py
checks they agree on a corpus of good and deliberately broken messages plus fuzzing.

It takes the same inputs as the models: wire maps straight from msgpack (decode) and numpy
arrays / Python values (building a message), and it reads dtypes, ranks and defaults from the
model fields, so the schema itself is still declared once, above.

Each such type registers its shape rule with `register` (protocol/schemas.py does, beside the
messages); `fast_state` and `fast_from_wire` are what the models and the codec call.
"""

from __future__ import annotations

import re
import sys
import typing
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from hammer.protocol.fields import MAX_NDIM, NAME_RE, WIRE_DTYPES, ArrayField
from pydantic import BaseModel

if TYPE_CHECKING:
    from hammer.protocol.schemas import Message

class Decline(Exception):
    """The fast path does not vouch for this input; pydantic decides."""


_setattr = object.__setattr__
_FAST_OK = sys.byteorder == "little"  # wire arrays are little-endian: decode them without a swap
try:  # the C function behind np.count_nonzero, without its Python dispatch wrapper (numpy >= 2)
    from numpy._core.multiarray import count_nonzero
except ImportError:  # pragma: no cover - numpy 1.x
    count_nonzero = np.count_nonzero
# env_idx is almost always 0..K-1: comparing its bytes with these proves "unique and >= 0" at once.
_ARANGE_BYTES = np.arange(4096, dtype="<i8").tobytes()
_RUN_MATCH = re.compile(NAME_RE.pattern.removeprefix("^").removesuffix("$")).fullmatch


def set_state(obj: BaseModel, values: dict[str, Any], fields_set: set[str]) -> None:
    """What pydantic's `model_construct` sets on a model (extra="forbid", no private attributes)."""
    _setattr(obj, "__dict__", values)
    _setattr(obj, "__pydantic_fields_set__", fields_set)
    _setattr(obj, "__pydantic_extra__", None)
    _setattr(obj, "__pydantic_private__", None)


def _nonneg_int(v: Any) -> int:
    if type(v) is not int or v < 0:
        raise Decline
    return v


def _run(v: Any) -> str:
    if type(v) is not str or (v and _RUN_MATCH(v) is None):
        raise Decline
    return v


def _sender(v: Any) -> str:
    if type(v) is not str or len(v) > 128:
        raise Decline
    return v


def _array_check(spec: ArrayField, optional: bool) -> Callable[[Any], np.ndarray | None]:
    """The checks of `ArrayField.validate` (plus array_from_wire) for one field."""
    names = frozenset(spec.dtypes)
    by_dtype = {WIRE_DTYPES[n]: n for n in spec.dtypes}  # little-endian = native here
    ndims = frozenset(spec.ndims if spec.ndims is not None else range(MAX_NDIM + 1))

    def check(v: Any) -> np.ndarray | None:
        if type(v) is np.ndarray:
            if v.dtype not in by_dtype or v.ndim not in ndims:
                raise Decline
            a = v
        elif type(v) is dict:
            name, shape, data = v.get("dtype"), v.get("shape"), v.get("data")
            if (len(v) != 3 or type(name) is not str or name not in names or type(shape) is not list
                    or len(shape) not in ndims or type(data) is not bytes):
                raise Decline
            count = 1
            for n in shape:
                if type(n) is not int or n < 0:
                    raise Decline
                count *= n
            dtype = WIRE_DTYPES[name]
            if count * dtype.itemsize != len(data):
                raise Decline
            if name == "bool" and data.translate(None, b"\x00\x01"):  # any byte other than 0 / 1 left
                raise Decline
            # A copy into a bytearray: writable, native (little-endian) and does not pin the payload.
            a = np.frombuffer(bytearray(data), dtype).reshape(shape)
        elif v is None and optional:
            return None
        else:
            raise Decline
        if a.dtype.kind == "f" and count_nonzero(np.isfinite(a)) != a.size:
            raise Decline
        return a

    return check


def _env_idx(check: Callable[[Any], np.ndarray | None]) -> Callable[[Any], np.ndarray]:
    def env_idx(v: Any) -> np.ndarray:
        a = check(v)
        if a.size and not _ARANGE_BYTES.startswith(a.tobytes()):  # int64 native = little-endian here
            idx = a.tolist()
            if min(idx) < 0 or len(set(idx)) != len(idx):
                raise Decline
        return a

    return env_idx


def _field_check(cls: type[Message], name: str, info: Any) -> Callable[[Any], Any]:
    """The fast check of one model field, from its declaration where it is an array."""
    if name == "type":
        tag = cls.TYPE

        def type_tag(v: Any) -> str:
            if type(v) is not str or v != tag:
                raise Decline
            return v

        return type_tag
    version = cls.model_fields["v"].default

    def _version(v: Any) -> int:
        if type(v) is not int or v != version:
            raise Decline
        return v

    scalar = {"v": _version, "run": _run, "sender": _sender, "step": _nonneg_int, "ts": _nonneg_int,
              "seq": _nonneg_int, "agent": _nonneg_int, "policy_version": _nonneg_int}
    if name in scalar:
        return scalar[name]
    for meta in info.metadata:
        if isinstance(meta, ArrayField):
            check = _array_check(meta, optional=False)
            return _env_idx(check) if name == "env_idx" else check
    args = typing.get_args(info.annotation)
    if type(None) in args:
        for arg in args:
            for meta in getattr(arg, "__metadata__", ()):
                if isinstance(meta, ArrayField):
                    return _array_check(meta, optional=True)
    raise TypeError(f"{cls.__name__}.{name}: no fast-path check for this field; add one in protocol/fast_path.py")


def fast_validator(cls: type[Message], shapes: Callable[[dict, int], str | None]) -> Callable:
    """validate(data) -> (field values, fields set) exactly as pydantic would produce them, or raise."""
    fields = []
    for name, info in cls.model_fields.items():
        if info.default_factory is not None:
            default, factory = None, info.default_factory
        else:
            default, factory = (Decline if info.is_required() else info.default), None
        fields.append((name, _field_check(cls, name, info), default, factory))
    known = frozenset(cls.model_fields)

    def validate(data: dict) -> tuple[dict[str, Any], set[str]]:
        if not _FAST_OK or not known.issuperset(data):  # unknown field (or a non-str key)
            raise Decline
        values = {}
        for name, check, default, factory in fields:
            if name in data:
                values[name] = check(data[name])
            elif factory is not None:
                values[name] = factory()
            elif default is Decline:  # required and missing
                raise Decline
            else:
                values[name] = default
        fields_set = set(data)
        added = shapes(values, values["env_idx"].shape[0])
        if added is not None:  # the pydantic model validator assigned it, which marks it set
            fields_set.add(added)
        return values, fields_set

    return validate


_FAST: dict[type, Callable[[dict], tuple[dict[str, Any], set[str]]]] = {}


def register(cls: type[Message], shapes: Callable[[dict, int], str | None]) -> None:
    """Give message type `cls` a fast path; `shapes(values, k)` checks what its fields' own checks
    cannot (sizes that must agree, value ranges) and raises `Decline`, or names a field it filled."""
    _FAST[cls] = fast_validator(cls, shapes)


def fast_types() -> frozenset[type]:
    """The message types that have a fast path."""
    return frozenset(_FAST)


def fast_state(cls: type[Message], data: dict) -> tuple[dict[str, Any], set[str]] | None:
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
    state = fast_state(cls, d)
    if state is None:
        return None
    msg = cls.__new__(cls)
    set_state(msg, *state)
    return msg
