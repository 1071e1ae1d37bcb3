"""The msgpack wire codec: message model <-> bytes, validating everything on the way in.

Layout (see docs/wire-format.md): one msgpack map per message, string keys = the model's field
names, arrays as plain maps {"dtype", "shape", "data"}. No ext types and no pickle, so any
msgpack library in any language can read and write it.

`decode` is the trust boundary: it never returns a message that failed a check, and every
failure is a `ProtocolError` subclass naming the field, so a subscriber can count and skip it.
The hot message types are validated by the hand-written fast path of `protocol.schemas` first;
whatever it declines is validated by the pydantic models, which also produce every error.
"""

from __future__ import annotations

import threading
from typing import Any

import msgpack
import numpy as np
from hammer.protocol.dims import Dims
from hammer.protocol.errors import (
    REASON_TO_ERROR,
    DecodeError,
    FieldError,
    NonFiniteError,
    ProtocolError,
    RunMismatchError,
    SizeError,
    TypeTagError,
    VersionError,
)
from hammer.protocol.fast_path import fast_from_wire
from hammer.protocol.fields import NAME_OF, array_to_wire
from hammer.protocol.schemas import MESSAGE_TYPES, SCHEMA_VERSION, Message
from pydantic import BaseModel, ValidationError

Expected = type[Message] | tuple[type[Message], ...] | None


_PLAIN = frozenset({int, str, bool, float, bytes, type(None)})


def _to_wire(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return array_to_wire(value)
    if isinstance(value, BaseModel):
        return {name: _to_wire(getattr(value, name)) for name in _field_names(type(value))}
    if isinstance(value, dict):
        return {k: _to_wire(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_to_wire(v) for v in value]
    return value


_FIELDS: dict[type, tuple[str, ...]] = {}


def _field_names(cls: type[BaseModel]) -> tuple[str, ...]:
    names = _FIELDS.get(cls)
    if names is None:
        names = _FIELDS[cls] = tuple(cls.model_fields)
    return names


def _wire_value(v: Any) -> Any:
    """`_to_wire` with the common cases inlined (equal output, tested)."""
    t = type(v)
    if t in _PLAIN:
        return v
    if t is np.ndarray and (dtype := NAME_OF.get(v.dtype)) is not None:
        # A whitelisted little-endian dtype: array_to_wire without its checks and lookups.
        return {"dtype": dtype, "shape": list(v.shape), "data": v.tobytes()}
    if t is list:
        return [_wire_value(x) for x in v]
    if isinstance(v, BaseModel):
        values = v.__dict__
        return {n: x if type(x := values[n]) in _PLAIN else _wire_value(x) for n in _field_names(t)}
    return _to_wire(v)


def to_wire_dict(msg: Message, stamp: dict[str, Any] | None = None) -> dict[str, Any]:
    """The msgpack-ready map of a message; `stamp` overrides header fields (run, ts, seq, sender)."""
    values = msg.__dict__
    d = {}
    for name in _field_names(type(msg)):
        v = values[name]
        d[name] = v if type(v) in _PLAIN else _wire_value(v)
    if stamp:
        d.update(stamp)
    return d


def to_wire_dict_reference(msg: Message, stamp: dict[str, Any] | None = None) -> dict[str, Any]:
    """The generic walk `to_wire_dict` must equal (kept for tests and `hammer bench codec`)."""
    d = {}
    for name in _field_names(type(msg)):
        v = getattr(msg, name)
        d[name] = v if type(v) in _PLAIN else _to_wire(v)
    if stamp:
        d.update(stamp)
    return d


_packers = threading.local()


def _packb(obj: Any) -> bytes:
    """msgpack.packb with one reused Packer per thread (a Packer is not thread-safe)."""
    packer = getattr(_packers, "packer", None)
    if packer is None:
        packer = _packers.packer = msgpack.Packer(use_bin_type=True)
    try:
        return packer.pack(obj)
    except BaseException:
        _packers.packer = None  # never reuse a packer whose buffer an error may have left dirty
        raise


def encode(msg: Message, *, stamp: dict[str, Any] | None = None, max_bytes: int | None = None,
           fast: bool = True) -> bytes:
    """Encode a validated message. Raises SizeError if it exceeds its type's cap (fail at the sender).
    fast=False: the generic walk and a fresh packer (the reference, for tests and the bench)."""
    if not isinstance(msg, Message):
        raise TypeTagError(f"can only encode protocol messages, got {type(msg).__name__}")
    if fast:
        data = _packb(to_wire_dict(msg, stamp))
    else:
        data = msgpack.packb(to_wire_dict_reference(msg, stamp), use_bin_type=True)
    cap = max_bytes if max_bytes is not None else type(msg).MAX_BYTES
    if len(data) > cap:
        raise SizeError(f"{type(msg).__name__} encodes to {len(data)} bytes, over the cap of {cap}")
    return data


_ALL_TYPES = tuple(MESSAGE_TYPES.values())
_ALL_CAP = max(t.MAX_BYTES for t in _ALL_TYPES)


def _expected_types(expected: Expected) -> tuple[type[Message], ...]:
    if expected is None:
        return _ALL_TYPES
    if isinstance(expected, type):
        return (expected,)
    return tuple(expected)


def _reject_ext(code: int, data: bytes) -> Any:
    raise DecodeError(f"msgpack ext type {code} is not part of the wire format")


def _from_validation_error(e: ValidationError) -> ProtocolError:
    err = e.errors(include_url=False)[0]
    ctx = err.get("ctx") or {}
    loc = ".".join(str(p) for p in err["loc"])
    field = ctx.get("field") or loc or None
    if field and loc and loc != field and loc.startswith(field + "."):
        field = loc  # keep the nested path, e.g. arrays.reward
    kind = err["type"]
    cls = REASON_TO_ERROR.get(kind)
    if cls is None:
        cls = NonFiniteError if kind == "finite_number" else FieldError
    msg = ctx.get("msg") or err["msg"]
    if cls is FieldError and kind not in ("field",):
        got = err.get("input")
        msg = f"{msg} (got {type(got).__name__})" if kind != "missing" else msg
    more = e.error_count() - 1
    if more:
        msg += f" (+{more} more error{'s' if more > 1 else ''})"
    return cls(msg, field)


def decode(
    data: bytes | bytearray | memoryview,
    expected: Expected = None,
    dims: Dims | None = None,
    *,
    max_bytes: int | None = None,
    run: str | None = None,
    fast: bool = True,
) -> Message:
    """Decode and validate one message.

    expected: the message type(s) accepted (None = any); dims: declared dimensions to check;
    max_bytes: size cap overriding the per-type caps; run: reject messages of another run id;
    fast=False: pydantic only (the reference the fast path is tested and benchmarked against).
    Raises a ProtocolError subclass on any failure.
    """
    types = _expected_types(expected)
    if not isinstance(data, bytes):
        if isinstance(data, bytearray | memoryview):
            data = bytes(data)
        else:
            raise DecodeError(f"payload must be bytes, got {type(data).__name__}")
    if max_bytes is not None:
        cap = max_bytes
    elif types is _ALL_TYPES:
        cap = _ALL_CAP
    elif len(types) == 1:
        cap = types[0].MAX_BYTES
    else:
        cap = max(t.MAX_BYTES for t in types)
    if len(data) > cap:
        raise SizeError(f"payload of {len(data)} bytes is over the cap of {cap}")
    try:
        d = msgpack.unpackb(data, raw=False, strict_map_key=True, use_list=True, ext_hook=_reject_ext)
    except ProtocolError:
        raise
    except Exception as e:  # noqa: BLE001 - msgpack raises ValueError, FormatError, StackError, ExtraData, TypeError...
        raise DecodeError(f"not well-formed msgpack: {type(e).__name__}: {e}") from None
    if not isinstance(d, dict):
        raise DecodeError(f"top level must be a map, got {type(d).__name__}")

    v = d.get("v")
    if type(v) is not int:
        raise VersionError(f"missing or non-integer schema version (got {v!r})", "v")
    if v != SCHEMA_VERSION:
        raise VersionError(f"schema version {v}, this code speaks {SCHEMA_VERSION}", "v")
    tag = d.get("type")
    cls = MESSAGE_TYPES.get(tag) if isinstance(tag, str) else None
    if cls is None:
        raise TypeTagError(f"unknown type tag {tag!r} (known: {', '.join(MESSAGE_TYPES)})", "type")
    if cls not in types:
        raise TypeTagError(f"got {tag!r}, expected {' or '.join(t.TYPE for t in types)}", "type")
    if max_bytes is None and len(data) > cls.MAX_BYTES:
        raise SizeError(f"{tag} payload of {len(data)} bytes is over its cap of {cls.MAX_BYTES}")

    msg = fast_from_wire(cls, d) if fast else None
    if msg is None:  # not a hot type, or the fast path declined: pydantic accepts it or names the error
        try:
            msg = cls.model_validate(d)
        except ValidationError as e:
            raise _from_validation_error(e) from None
    if not msg.run:
        raise FieldError("is empty: messages on the wire must carry their run id", "run")
    if run is not None and msg.run != run:
        raise RunMismatchError(f"message of run {msg.run!r} received by run {run!r}", "run")
    if dims is not None:
        msg.check_dims(dims)
    return msg

