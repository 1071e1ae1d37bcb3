"""The field types messages are made of: wire dtypes, numpy array fields, names, size bounds.

No pydantic here (nor anywhere on the wire path): the messages are msgspec Structs
(protocol/schemas.py) whose wire forms msgspec checks (types, strict ints, lengths, patterns), and
what msgspec cannot say about an array (its dtype, rank, byte count, finiteness) is checked here,
by `ArraySpec.take`, in each message's `__post_init__`, which msgspec runs both when code builds a
message and when it decodes one. So a NaN or a wrong dtype is caught at the sender as well as at
the receiver, by the same code.

An array travels as a msgpack array `[dtype code, shape, data]` (`DTYPE_CODES`, a list of ints,
raw little-endian C-order bytes; never pickled). A field declares the dtypes it holds in memory
and the narrower wire dtypes it also accepts: discrete action ids are int64 in memory and go as
uint8 when every id fits; float32 observations and messages may go as float16 when a sender opts
in (`half=True` of `codec.encode`), and are float32 again after decoding.
"""

from __future__ import annotations

import re
import sys
from dataclasses import dataclass
from typing import Any

import numpy as np
from hammer.protocol.errors import DTypeError, FieldError, NonFiniteError, ProtocolError, ShapeError

# dtype names -> numpy dtype (always little-endian on the wire).
WIRE_DTYPES: dict[str, np.dtype] = {
    "float32": np.dtype("<f4"),
    "float64": np.dtype("<f8"),
    "int64": np.dtype("<i8"),
    "int32": np.dtype("<i4"),
    "uint8": np.dtype("u1"),
    "bool": np.dtype("?"),
    "float16": np.dtype("<f2"),
}
# The small int that names a dtype on the wire (one msgpack byte instead of a string).
DTYPE_CODES: dict[str, int] = {"bool": 0, "uint8": 1, "int32": 2, "int64": 3, "float16": 4, "float32": 5,
                               "float64": 6}
CODE_NAMES: dict[int, str] = {c: n for n, c in DTYPE_CODES.items()}
# What an experience chunk's arrays may hold: every dtype but the float16 of the opt-in compact observations.
ARRAY_DTYPES = ("float32", "float64", "int64", "int32", "uint8", "bool")
FLOAT_DTYPES = frozenset({"float32", "float64", "float16"})
_NATIVE: dict[str, np.dtype] = {name: dt.newbyteorder("=") for name, dt in WIRE_DTYPES.items()}
# dtype -> wire name, looked up by dtype object because `dtype.name` is slow Python code.
NAME_OF: dict[np.dtype, str] = {dt: name for name, dt in WIRE_DTYPES.items()}
_LITTLE = sys.byteorder == "little"


def dtype_name(dt: np.dtype) -> str:
    """Wire name of a numpy dtype, or its numpy name when it is not on the whitelist."""
    name = NAME_OF.get(dt)
    if name is None:
        name = NAME_OF.get(dt.newbyteorder("<"), dt.name) if dt.byteorder == ">" else dt.name
    return name


MAX_NDIM = 8

MiB = 1 << 20
DEFAULT_MAX_BYTES = 4 * MiB
# Everything of a message but its array bytes, bounded: the type tag, version, ints, the sender
# (<= 128 chars), names and up to four array headers ([code, shape (<= 8 ints), bin header]).
HEADER_BYTES = 2048

NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
NAME_RULE = "1-64 chars of letters, digits, '_', '-', '.', starting with a letter or digit"
ARRAY_NAME_PATTERN = r"^[A-Za-z_][A-Za-z0-9_.]{0,63}$"


def check_name(value: str, what: str) -> str:
    """Validate a run id / role name used inside key expressions (raises ValueError)."""
    if not isinstance(value, str) or not NAME_RE.match(value):
        raise ValueError(f"invalid {what} {value!r}: use {NAME_RULE}")
    return value


def array_to_wire(a: np.ndarray, name: str | None = None) -> list:
    """The wire form of an array: [dtype code, shape, raw little-endian bytes] (`name`: the wire
    dtype to write, default the array's own)."""
    if name is None:
        name = NAME_OF.get(a.dtype) or dtype_name(a.dtype)
    wire = WIRE_DTYPES.get(name)
    if wire is None:
        raise DTypeError(f"dtype {name} is not allowed on the wire ({', '.join(WIRE_DTYPES)})")
    if a.dtype != wire:
        a = a.astype(wire)
    # tobytes() always writes C order, whatever the memory layout of `a`.
    return [DTYPE_CODES[name], list(a.shape), a.tobytes()]


def array_from_wire(v: Any, field: str | None, allowed: frozenset[str] | None = None) -> np.ndarray:
    """A native, writable numpy array from its wire form; DTypeError/ShapeError/FieldError naming `field`."""
    if type(v) not in (tuple, list) or len(v) != 3:
        raise FieldError("an array must be [dtype code, shape, data]", field)
    code, shape, data = v
    name = CODE_NAMES.get(code) if type(code) is int else None
    if name is None:
        raise DTypeError(f"dtype code {code!r} is not one of {DTYPE_CODES}", field)
    if allowed is not None and name not in allowed:
        raise DTypeError(f"dtype {name} not allowed here, need one of {sorted(allowed)}", field)
    if type(shape) not in (list, tuple) or len(shape) > MAX_NDIM or not all(type(n) is int and n >= 0 for n in shape):
        raise ShapeError(f"shape must be a list of at most {MAX_NDIM} non-negative ints, got {shape!r}", field)
    if type(data) is not bytes:
        raise FieldError(f"array data must be msgpack bin, got {type(data).__name__}", field)
    dtype = WIRE_DTYPES[name]
    count = 1
    for n in shape:
        count *= n
    if count * dtype.itemsize != len(data):
        raise ShapeError(f"shape {list(shape)} of {name} needs {count * dtype.itemsize} bytes, got {len(data)}", field)
    if name == "bool" and data.translate(None, b"\x00\x01"):  # any byte other than 0 / 1 left
        raise FieldError("bool array bytes must be 0 or 1", field)
    if _LITTLE:  # a copy into a bytearray: writable, native and does not pin the payload
        return np.frombuffer(bytearray(data), dtype).reshape(shape)
    return np.frombuffer(data, dtype).reshape(shape).astype(_NATIVE[name], copy=True)


try:  # the C function behind np.count_nonzero, without its Python dispatch (numpy >= 2): half the time of .all()
    from numpy._core.multiarray import count_nonzero
except ImportError:  # pragma: no cover - numpy 1.x
    count_nonzero = np.count_nonzero


def _finite(a: np.ndarray) -> bool:
    return count_nonzero(np.isfinite(a)) == a.size


@dataclass(frozen=True)
class ArraySpec:
    """What one array field holds: its dtypes in memory (`dtypes`), the extra narrower dtypes it
    accepts on the wire and widens on arrival (`wire`: wire name -> memory name), its ranks."""

    dtypes: tuple[str, ...]
    ndims: tuple[int, ...] | None = None
    wire: tuple[tuple[str, str], ...] = ()

    @property
    def wire_dtypes(self) -> frozenset[str]:
        return frozenset(self.dtypes) | {w for w, _ in self.wire}

    def take(self, value: Any, field: str) -> np.ndarray:
        """The field's array from what code passed (an ndarray) or what msgspec decoded (the wire
        form), checked: dtype, rank, finiteness. Raises a ProtocolError naming the field."""
        if type(value) is np.ndarray:
            a = value
            name = NAME_OF.get(a.dtype) or dtype_name(a.dtype)
            if name not in self.dtypes:
                hint = f"; cast with .astype(np.{self.dtypes[0]})" if self.dtypes[0] != "bool" else ""
                raise DTypeError(f"dtype {name} not allowed here, need one of {list(self.dtypes)}{hint}", field)
        elif type(value) in (tuple, list):
            a = array_from_wire(value, field, self._allowed)
            name = CODE_NAMES[value[0]]
            widen = self._widen.get(name)
            if widen is not None:
                a = a.astype(widen)
                name = NAME_OF[a.dtype]
        else:
            raise FieldError(f"expected a numpy array (or its wire form), got {type(value).__name__}", field)
        if self._ndims is not None and a.ndim not in self._ndims:
            raise ShapeError(f"needs {' or '.join(map(str, self.ndims))} dims, got shape {a.shape}", field)
        if a.ndim > MAX_NDIM:
            raise ShapeError(f"at most {MAX_NDIM} dims, got {a.ndim}", field)
        if name in FLOAT_DTYPES and a.size and not _finite(a):
            raise NonFiniteError("holds NaN or inf", field)
        return a

    def __post_init__(self) -> None:
        object.__setattr__(self, "_allowed", self.wire_dtypes)
        object.__setattr__(self, "_widen", {w: WIRE_DTYPES[m] for w, m in self.wire})
        object.__setattr__(self, "_ndims", frozenset(self.ndims) if self.ndims is not None else None)

    def json_schema(self) -> dict:
        desc = f"numpy array, {' or '.join(self.dtypes)}"
        if self.ndims is not None:
            desc += f", {' or '.join(map(str, self.ndims))} dims"
        if self.wire:
            desc += "; also accepted on the wire: " + ", ".join(f"{w} (read as {m})" for w, m in self.wire)
        return {
            "type": "array", "description": desc + ". [dtype code, shape, raw little-endian C-order bytes]",
            "prefixItems": [
                {"enum": sorted(DTYPE_CODES[n] for n in self.wire_dtypes),
                 "description": ", ".join(f"{DTYPE_CODES[n]} = {n}" for n in sorted(self.wire_dtypes,
                                                                                   key=DTYPE_CODES.get))},
                {"type": "array", "items": {"type": "integer", "minimum": 0}, "maxItems": MAX_NDIM},
                {"type": "string", "contentEncoding": "binary"},
            ],
            "minItems": 3, "maxItems": 3,
        }


def spec_error(e: Exception, field: str) -> ProtocolError:
    """A ProtocolError naming `field` for an error raised while checking it."""
    return e if isinstance(e, ProtocolError) else FieldError(str(e), field)


def empty_idx() -> np.ndarray:
    return np.zeros(0, dtype=np.int64)
