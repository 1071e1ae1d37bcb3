"""The msgpack wire codec: message model <-> bytes, validating everything on the way in.

Layout (see docs/wire-format.md): one msgpack map per message, string keys = the model's field
names, arrays as plain maps {"dtype", "shape", "data"}. No ext types and no pickle, so any
msgpack library in any language can read and write it.

`decode` is the trust boundary: it never returns a message that failed a check, and every
failure is a `ProtocolError` subclass naming the field, so a subscriber can count and skip it.
"""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np
from pydantic import BaseModel, ValidationError

from protocol.errors import (
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
from protocol.schemas import MESSAGE_TYPES, SCHEMA_VERSION, Dims, Message, array_to_wire

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


def to_wire_dict(msg: Message, stamp: dict[str, Any] | None = None) -> dict[str, Any]:
    """The msgpack-ready map of a message; `stamp` overrides header fields (run, ts, seq, sender)."""
    d = {}
    for name in _field_names(type(msg)):
        v = getattr(msg, name)
        d[name] = v if type(v) in _PLAIN else _to_wire(v)
    if stamp:
        d.update(stamp)
    return d


def encode(msg: Message, *, stamp: dict[str, Any] | None = None, max_bytes: int | None = None) -> bytes:
    """Encode a validated message. Raises SizeError if it exceeds its type's cap (fail at the sender)."""
    if not isinstance(msg, Message):
        raise TypeTagError(f"can only encode protocol messages, got {type(msg).__name__}")
    data = msgpack.packb(to_wire_dict(msg, stamp), use_bin_type=True)
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
) -> Message:
    """Decode and validate one message.

    expected: the message type(s) accepted (None = any); dims: declared dimensions to check;
    max_bytes: size cap overriding the per-type caps; run: reject messages of another run id.
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

