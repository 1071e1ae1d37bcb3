"""The msgpack wire codec: message <-> bytes, validating everything on the way in.

Layout (docs/wire-format.md): one msgpack array per message, `[type tag, v, step, env_idx,
sender, <the type's fields in order>]`, optional fields at their default left off the end;
arrays as `[dtype code, shape, data]`. No ext types and no pickle, so any msgpack library in any
language can read and write it.

`decode` is the trust boundary: it never returns a message that failed a check, and every
failure is a `ProtocolError` subclass naming the field, so a subscriber can count and skip it.
The version and the type tag are read first (the receiver's expected types, the type's size cap),
then msgspec decodes the payload into the tag's Struct, checking every field's wire type, and the
Struct's `__post_init__` checks its arrays (protocol/schemas.py). msgspec reports an error of its
own as a `ValidationError` whose text ends with the path (`$[3]`: the third field after the tag);
an error raised in `__post_init__` comes as its `__cause__`: both become the right ProtocolError.
"""

from __future__ import annotations

import re
import struct
from typing import Any

import msgspec
from hammer.protocol.dims import Dims, min_max
from hammer.protocol.errors import (
    DecodeError,
    FieldError,
    NonFiniteError,
    ProtocolError,
    SizeError,
    TypeTagError,
    VersionError,
)
from hammer.protocol.fields import DTYPE_CODES, ArraySpec, WireArray, array_to_wire, numpy_loaded
from hammer.protocol.schemas import (
    ACTION,
    MESSAGE_TYPES,
    SCHEMA_VERSION,
    TAGS,
    Action,
    GlobalState,
    LocalObs,
    Message,
    env_idx_to_wire,
    fields_of,
)

Expected = type[Message] | tuple[type[Message], ...] | None

_F16, _U8 = DTYPE_CODES["float16"], DTYPE_CODES["uint8"]
np: Any = None  # numpy, bound with the first numpy array encoded (the lite edge agent has none: `_array_lite`)
_F32: Any = None
count_nonzero: Any = None  # numpy's C count_nonzero (fields.py), bound with numpy
_NODEFAULT = object()
# Optional bool arrays whose usual value is sent as nil: every agent active, no fallback.
_NIL_WHEN = {(LocalObs, "active"): True, (GlobalState, "active"): True, (Action, "fallback"): False}


def _array(spec: ArraySpec, a: Any, half: bool, field: str) -> list:
    """The wire form of a field's array: ids as uint8 when they fit, float32 as float16 when the
    sender opted in (`half`) and the field accepts it."""
    if type(a) is WireArray:
        return _array_lite(spec, a, half, field)
    if np is None:
        _bind_numpy()
    if spec is ACTION and a.dtype == np.int64 and a.size:
        lo, hi = min_max(a)  # a list's min and max below 1,024 ids: no numpy reduction machinery
        if lo >= 0 and hi < 256:
            return [_U8, list(a.shape), a.astype(np.uint8).tobytes()]
    if half and a.dtype == _F32 and ("float16", "float32") in spec.wire:
        with np.errstate(over="ignore"):
            h = a.astype("<f2")
        if a.size and not np.isfinite(h).all():
            raise NonFiniteError("beyond float16's range (65504): send it as float32", field)
        return [_F16, list(a.shape), h.tobytes()]
    return array_to_wire(a)


def _bind_numpy() -> None:
    global _F32
    if numpy_loaded(globals()):
        _F32 = np.dtype("<f4")


def _array_lite(spec: ArraySpec, a: WireArray, half: bool, field: str) -> list:
    """`_array` of a WireArray (the lite edge agent): the same wire bytes numpy would write."""
    if spec is ACTION and a.dtype == "int64" and a.size:
        ids = a.tolist(flat=True)
        if min(ids) >= 0 and max(ids) < 256:
            return [_U8, list(a.shape), bytes(ids)]
    if half and a.dtype == "float32" and ("float16", "float32") in spec.wire:
        values = a.tolist(flat=True)
        try:
            h = struct.pack(f"<{len(values)}e", *values)
        except OverflowError:
            raise NonFiniteError("beyond float16's range (65504): send it as float32", field) from None
        return [_F16, list(a.shape), h]
    return array_to_wire(a)


def _plan(cls: type[Message]) -> list[tuple[str, Any, Any]]:
    """(field, how its value goes on the wire, its wire default) for each field of `cls`, in order."""
    plan = []
    for f in msgspec.structs.fields(cls):
        name = f.encode_name
        if f.default is not msgspec.NODEFAULT:
            default = f.default
        elif f.default_factory is not msgspec.NODEFAULT:
            default = f.default_factory()
        else:
            default = _NODEFAULT
        if name == "env_idx":
            conv, default = "env_idx", _NODEFAULT
        elif name in cls.ARRAYS:
            conv = ("array", cls.ARRAYS[name], _NIL_WHEN.get((cls, name)))
        elif name == "arrays":
            conv = "arrays"
        else:
            conv = None
        plan.append((name, conv, default))
    return plan


_PLANS = {cls: _plan(cls) for cls in MESSAGE_TYPES.values()}
_bind_numpy()  # where numpy came first (every role but the lite edge agent); else with the first numpy array




def to_wire(msg: Message, stamp: dict[str, Any] | None = None, half: bool = False) -> list:
    """The msgpack-ready array of a message: its type tag, then every field's wire value, without the
    optional ones at their default at the end. `stamp` overrides header fields (the sender)."""
    cls = type(msg)
    out: list[Any] = [cls.TAG]
    if np is None:  # numpy loaded since this module was (else the lite agent: WireArrays only)
        _bind_numpy()
    for name, conv, _ in _PLANS[cls]:
        v = getattr(msg, name) if not stamp or name not in stamp else stamp[name]
        if conv is None:
            out.append(v)
        elif conv == "env_idx":
            out.append(env_idx_to_wire(v))
        elif conv == "arrays":
            out.append({k: array_to_wire(a) for k, a in v.items()})
        elif v is None:
            out.append(None)
        else:
            _, spec, nil = conv
            if nil is not None and v.size and (count_nonzero(v) if type(v) is not WireArray
                                               else len(v.data) - v.data.count(0)) == (v.size if nil else 0):
                out.append(None)
            else:
                out.append(_array(spec, v, half, name))
    plan = _PLANS[cls]
    while len(out) > 1:  # the trailing fields at their default stay off the wire
        default = plan[len(out) - 2][2]
        if default is _NODEFAULT or type(out[-1]) is not type(default) or out[-1] != default:
            break
        out.pop()
    return out


_encoder = msgspec.msgpack.Encoder()


def encode(msg: Message, *, stamp: dict[str, Any] | None = None, max_bytes: int | None = None,
           half: bool = False) -> bytes:
    """Encode a validated message. Raises SizeError if it exceeds its type's cap (fail at the sender).
    stamp: header fields to set on the wire (the session stamps `sender`); half: float32
    observations and messages as float16 (opt-in: half the bytes, 3 significant digits)."""
    if not isinstance(msg, Message):
        raise TypeTagError(f"can only encode protocol messages, got {type(msg).__name__}")
    if stamp and not stamp.keys() <= _STAMPS:
        raise TypeError(f"stamp sets only {sorted(_STAMPS)}, got {sorted(stamp)}")
    data = _encoder.encode(to_wire(msg, stamp, half))
    cap = max_bytes if max_bytes is not None else type(msg).MAX_BYTES
    if len(data) > cap:
        raise SizeError(f"{type(msg).__name__} encodes to {len(data)} bytes, over the cap of {cap}")
    return data


_STAMPS = frozenset({"sender", "step"})
_ALL_TYPES = tuple(MESSAGE_TYPES.values())
_ALL_CAP = max(t.MAX_BYTES for t in _ALL_TYPES)
_DECODERS = {cls: msgspec.msgpack.Decoder(cls) for cls in _ALL_TYPES}


def _expected_types(expected: Expected) -> tuple[type[Message], ...]:
    if expected is None:
        return _ALL_TYPES
    if isinstance(expected, type):
        return (expected,)
    return tuple(expected)


_PATH = re.compile(r" - at `(?:key` in `)?\$\[(\d+)\]([^`]*)`$")
_LENGTH = re.compile(r"Expected `array` of at (least|most) length (\d+), got (\d+)$")


def _from_validation_error(e: msgspec.ValidationError, cls: type[Message]) -> ProtocolError:
    """The ProtocolError of a msgspec ValidationError, naming the field."""
    cause = e.__cause__
    if isinstance(cause, ProtocolError):  # raised by a check in __post_init__
        return cause
    names = ("type", *fields_of(cls))
    text = str(e)
    if cause is not None:
        return FieldError(str(cause), None)
    if m := _PATH.search(text):
        i = int(m[1])
        field = names[i] if i < len(names) else None
        if field in ("arrays", "meta", "counters", "gauges", "args") and "key" in text[m.start():]:
            text = text[:m.start()] + " (a name)"
        else:
            text = text[:m.start()]
        return FieldError(text, field)
    if m := _LENGTH.search(text):
        got = int(m[3])
        if m[1] == "least":
            return FieldError(f"missing (the message has {got - 1} of its fields)",
                              names[got] if got < len(names) else None)
        # msgspec counts a tagged message's elements after the type tag, both the most and what came
        return FieldError(f"unknown: {got - int(m[2])} more element(s) than {cls.TYPE} has", None)
    return FieldError(text, None)


def _peek(data: bytes) -> tuple[Any, Any]:
    """(type tag, v) of a payload: read from its first bytes when they are the usual small ints,
    else from a generic decode (which also names a malformed payload)."""
    b0 = data[0] if data else -1
    i = 1 if 0x90 <= b0 <= 0x9F else 3 if b0 == 0xDC else 0
    if i and len(data) > i + 1 and data[i] < 0x80 and data[i + 1] < 0x80:
        return data[i], data[i + 1]
    try:
        obj = msgspec.msgpack.decode(data)
    except Exception as e:  # noqa: BLE001 - msgspec.DecodeError, RecursionError, ...
        raise DecodeError(f"not well-formed msgpack: {type(e).__name__}: {e}") from None
    if not isinstance(obj, list):
        raise DecodeError(f"top level must be an array, got {type(obj).__name__}")
    if len(obj) < 2:
        raise VersionError(f"missing schema version (an array of {len(obj)})", "v")
    return obj[0], obj[1]


def decode(
    data: bytes | bytearray | memoryview,
    expected: Expected = None,
    dims: Dims | None = None,
    *,
    max_bytes: int | None = None,
) -> Message:
    """Decode and validate one message.

    expected: the message type(s) accepted (None = any); dims: declared dimensions to check;
    max_bytes: size cap overriding the per-type caps. Raises a ProtocolError subclass on any failure.
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
    tag, v = _peek(data)
    if type(v) is not int:
        raise VersionError(f"missing or non-integer schema version (got {v!r})", "v")
    if v != SCHEMA_VERSION:
        raise VersionError(f"schema version {v}, this code speaks {SCHEMA_VERSION}", "v")
    cls = TAGS.get(tag) if type(tag) is int else None
    if cls is None:
        raise TypeTagError(f"unknown type tag {tag!r} (known: {', '.join(f'{c.TAG} {n}' for n, c in MESSAGE_TYPES.items())})",
                           "type")
    if cls not in types:
        raise TypeTagError(f"got {cls.TYPE!r}, expected {' or '.join(t.TYPE for t in types)}", "type")
    if max_bytes is None and len(data) > cls.MAX_BYTES:
        raise SizeError(f"{cls.TYPE} payload of {len(data)} bytes is over its cap of {cls.MAX_BYTES}")
    try:
        msg = _DECODERS[cls].decode(data)
    except msgspec.ValidationError as e:
        raise _from_validation_error(e, cls) from None
    except msgspec.DecodeError as e:
        raise DecodeError(f"not well-formed msgpack: {e}") from None
    except ProtocolError:
        raise
    except Exception as e:  # noqa: BLE001 - whatever a hostile payload provokes is a rejection, never a crash
        raise FieldError(f"{type(e).__name__}: {e}", None) from None
    if dims is not None:
        msg.check_dims(dims)
    return msg
