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

import contextlib
import math
import re
import sys
from array import array
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from hammer.protocol.errors import DTypeError, FieldError, NonFiniteError, ProtocolError, ShapeError

if TYPE_CHECKING:
    import numpy

np: Any = None  # numpy once this process has loaded it (`numpy_loaded`); None on the lite edge path

# dtype name -> (numpy's little-endian dtype string, bytes per item, the `array`/`struct` code).
_DTYPE_SPECS: dict[str, tuple[str, int, str]] = {
    "float32": ("<f4", 4, "f"), "float64": ("<f8", 8, "d"), "int64": ("<i8", 8, "q"), "int32": ("<i4", 4, "i"),
    "uint8": ("u1", 1, "B"), "bool": ("?", 1, "B"), "float16": ("<f2", 2, "e"),
}
ITEMSIZE: dict[str, int] = {name: size for name, (_, size, _) in _DTYPE_SPECS.items()}
_FORCE_LITE = False  # tests only (`lite_arrays`): the pure-Python checks in a process that has numpy
_LAZY_USERS: list[dict] = []  # the module globals whose `np` is bound by `numpy_loaded`


def numpy_loaded(g: dict | None = None) -> bool:
    """Whether this process has imported numpy: then arrays are numpy arrays and the module whose
    globals are `g` gets it bound as `np`. Never imports numpy itself (the lite edge agent must not)."""
    m = None if _FORCE_LITE else sys.modules.get("numpy")
    if m is None:
        return False
    _bind(m)
    if g is not None:
        g["np"] = m
        if "count_nonzero" in g:
            g["count_nonzero"] = count_nonzero
        if g not in _LAZY_USERS:
            _LAZY_USERS.append(g)
    return True


def _bind(m: Any) -> None:
    """Bind numpy and the tables built from it in this module."""
    global np, count_nonzero
    if np is not None:
        return
    np = m
    WIRE_DTYPES.update({name: m.dtype(spec) for name, (spec, _, _) in _DTYPE_SPECS.items()})
    _NATIVE.update({name: dt.newbyteorder("=") for name, dt in WIRE_DTYPES.items()})
    NAME_OF.update({dt: name for name, dt in WIRE_DTYPES.items()})
    try:  # the C function behind np.count_nonzero, without its Python dispatch (numpy >= 2): half the time of .all()
        from numpy._core.multiarray import count_nonzero as c
    except ImportError:  # pragma: no cover - numpy 1.x
        c = m.count_nonzero
    count_nonzero = c


@contextlib.contextmanager
def lite_arrays():
    """Tests only: the pure-Python array path in this process (which has numpy), as on the lite edge agent."""
    global _FORCE_LITE, np
    saved = [(g, g.get("np")) for g in _LAZY_USERS]
    saved_np, _FORCE_LITE = np, True
    for g, _ in saved:
        g["np"] = None
    np = None
    try:
        yield
    finally:
        _FORCE_LITE, np = False, saved_np
        for g, v in saved:
            g["np"] = v


# dtype names -> numpy dtype (always little-endian on the wire); filled once numpy is loaded.
WIRE_DTYPES: dict[str, numpy.dtype] = {}
# The small int that names a dtype on the wire (one msgpack byte instead of a string).
DTYPE_CODES: dict[str, int] = {"bool": 0, "uint8": 1, "int32": 2, "int64": 3, "float16": 4, "float32": 5,
                               "float64": 6}
CODE_NAMES: dict[int, str] = {c: n for n, c in DTYPE_CODES.items()}
# What an experience chunk's arrays may hold: every dtype but the float16 of the opt-in compact observations.
ARRAY_DTYPES = ("float32", "float64", "int64", "int32", "uint8", "bool")
FLOAT_DTYPES = frozenset({"float32", "float64", "float16"})
_NATIVE: dict[str, numpy.dtype] = {}
# dtype -> wire name, looked up by dtype object because `dtype.name` is slow Python code.
NAME_OF: dict[numpy.dtype, str] = {}
_LITTLE = sys.byteorder == "little"


def dtype_name(dt: numpy.dtype) -> str:
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


def array_to_wire(a: Any, name: str | None = None) -> list:
    """The wire form of an array: [dtype code, shape, raw little-endian bytes] (`name`: the wire
    dtype to write, default the array's own)."""
    if type(a) is WireArray:
        if name is not None and name != a.dtype:
            a = WireArray.of(name, a.shape, a.tolist(flat=True))
        return [DTYPE_CODES[a.dtype], list(a.shape), a.tobytes()]
    if name is None:
        name = NAME_OF.get(a.dtype) or dtype_name(a.dtype)
    wire = WIRE_DTYPES.get(name)
    if wire is None:
        raise DTypeError(f"dtype {name} is not allowed on the wire ({', '.join(_DTYPE_SPECS)})")
    if a.dtype != wire:
        a = a.astype(wire)
    # tobytes() always writes C order, whatever the memory layout of `a`.
    return [DTYPE_CODES[name], list(a.shape), a.tobytes()]


def _checked_wire(v: Any, field: str | None, allowed: frozenset[str] | None) -> tuple[str, Any, bytes]:
    """(dtype name, shape, data) of an array's wire form, every check of `array_from_wire` made:
    the one code both the numpy and the pure-Python path run, so their verdicts cannot differ."""
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
    size = ITEMSIZE[name]
    count = 1
    for n in shape:
        count *= n
    if count * size != len(data):
        raise ShapeError(f"shape {list(shape)} of {name} needs {count * size} bytes, got {len(data)}", field)
    if name == "bool" and data.translate(None, b"\x00\x01"):  # any byte other than 0 / 1 left
        raise FieldError("bool array bytes must be 0 or 1", field)
    return name, shape, data


def array_from_wire(v: Any, field: str | None, allowed: frozenset[str] | None = None) -> numpy.ndarray:
    """A native, writable numpy array from its wire form; DTypeError/ShapeError/FieldError naming `field`."""
    name, shape, data = _checked_wire(v, field, allowed)
    dtype = WIRE_DTYPES[name]
    if _LITTLE:  # a copy into a bytearray: writable, native and does not pin the payload
        return np.frombuffer(bytearray(data), dtype).reshape(shape)
    return np.frombuffer(data, dtype).reshape(shape).astype(_NATIVE[name], copy=True)


count_nonzero: Any = None  # numpy's C count_nonzero, bound with numpy (`_bind`)


def _finite(a: numpy.ndarray) -> bool:
    return count_nonzero(np.isfinite(a)) == a.size


class WireArray:
    """An array field where numpy is not loaded (the lite edge agent): its checked values as their
    little-endian wire bytes with their dtype name (`float32`, `int64`, `bool`, ... as on the wire) and shape; what the
    messages and the lite agent need of an array (`shape`, `ndim`, `size`, `tolist`, `tobytes`,
    equality), nothing more. Built only through `ArraySpec.take` or `WireArray.of`."""

    __slots__ = ("data", "dtype", "shape")

    def __init__(self, dtype: str, shape: tuple[int, ...], data: bytes) -> None:
        self.dtype, self.shape, self.data = dtype, shape, data

    @classmethod
    def of(cls, dtype: str, shape: tuple[int, ...], values: Any) -> WireArray:
        """From flat Python values (floats rounded to the dtype as numpy's astype does)."""
        if dtype == "float16":
            import struct

            return cls(dtype, tuple(shape), struct.pack(f"<{len(values)}e", *values))
        a = array(_DTYPE_SPECS[dtype][2], values)
        if not _LITTLE:  # pragma: no cover - big-endian hosts
            a.byteswap()
        return cls(dtype, tuple(shape), a.tobytes())

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def size(self) -> int:
        return len(self.data) // ITEMSIZE[self.dtype]

    def tobytes(self) -> bytes:
        return self.data

    def tolist(self, flat: bool = False) -> list:
        """The values as Python ints, floats or bools; nested by the shape unless `flat` (as numpy's)."""
        if self.dtype == "float16":
            import struct

            values: list = list(struct.unpack(f"<{self.size}e", self.data))
        else:
            a = array(_DTYPE_SPECS[self.dtype][2])
            a.frombytes(self.data)
            if not _LITTLE:  # pragma: no cover - big-endian hosts
                a.byteswap()
            values = a.tolist()
            if self.dtype == "bool":
                values = [v != 0 for v in values]
        if flat or len(self.shape) == 1:
            return values
        if not self.shape:
            return values[0]
        for n in reversed(self.shape[1:]):
            values = [values[i:i + n] for i in range(0, len(values), n)]
        return values

    def __len__(self) -> int:
        return self.shape[0]

    def __eq__(self, other: object) -> bool:
        return (type(other) is WireArray and self.dtype == other.dtype and self.shape == other.shape
                and self.data == other.data)

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"WireArray({self.dtype}, {self.shape}, {self.tolist()})"


def _finite_values(a: WireArray) -> bool:
    return all(map(math.isfinite, a.tolist(flat=True)))


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

    def take(self, value: Any, field: str) -> Any:
        """The field's array from what code passed (an ndarray) or what msgspec decoded (the wire
        form), checked: dtype, rank, finiteness. Raises a ProtocolError naming the field. A numpy
        array where numpy is loaded, else a `WireArray` (`take_lite`: the same checks)."""
        if np is None and not numpy_loaded():
            return self.take_lite(value, field)
        if type(value) is np.ndarray:
            a = value
            name = NAME_OF.get(a.dtype) or dtype_name(a.dtype)
            if name not in self.dtypes:
                hint = f"; cast with .astype(np.{self.dtypes[0]})" if self.dtypes[0] != "bool" else ""
                raise DTypeError(f"dtype {name} not allowed here, need one of {list(self.dtypes)}{hint}", field)
        elif type(value) in (tuple, list) or type(value) is WireArray:
            if type(value) is WireArray:  # built before numpy was loaded (a lite process that loaded it since)
                value = [DTYPE_CODES[value.dtype], list(value.shape), value.data]
            name, shape, data = _checked_wire(value, field, self._allowed)  # array_from_wire, one call less
            if _LITTLE:  # a copy into a bytearray: writable, native and does not pin the payload
                a = np.frombuffer(bytearray(data), WIRE_DTYPES[name]).reshape(shape)
            else:  # pragma: no cover - big-endian hosts
                a = np.frombuffer(data, WIRE_DTYPES[name]).reshape(shape).astype(_NATIVE[name], copy=True)
            widen = self._widen.get(name)
            if widen is not None:
                a = a.astype(WIRE_DTYPES[widen])
                name = widen
        else:
            raise FieldError(f"expected a numpy array (or its wire form), got {type(value).__name__}", field)
        return self._checked(a, name, field, _finite)

    def take_lite(self, value: Any, field: str) -> WireArray:
        """`take` without numpy, check for check: the array as a `WireArray`."""
        if type(value) is WireArray:
            a = value
            name = a.dtype
            if name not in self.dtypes:
                hint = f"; cast with .astype(np.{self.dtypes[0]})" if self.dtypes[0] != "bool" else ""
                raise DTypeError(f"dtype {name} not allowed here, need one of {list(self.dtypes)}{hint}", field)
        elif type(value) in (tuple, list):
            name, shape, data = _checked_wire(value, field, self._allowed)
            a = WireArray(name, tuple(shape), data)
            widen = self._widen.get(name)
            if widen is not None:
                a = WireArray.of(widen, a.shape, a.tolist(flat=True))
                name = widen
        else:
            raise FieldError(f"expected a numpy array (or its wire form), got {type(value).__name__}", field)
        return self._checked(a, name, field, _finite_values)

    def _checked(self, a: Any, name: str, field: str, finite: Any) -> Any:
        """The checks `take` and `take_lite` share, on a numpy array or a `WireArray` (`finite`: the
        finiteness test of that kind): dims, then finite floats."""
        if self._ndims is not None and a.ndim not in self._ndims:
            raise ShapeError(f"needs {' or '.join(map(str, self.ndims))} dims, got shape {a.shape}", field)
        if a.ndim > MAX_NDIM:
            raise ShapeError(f"at most {MAX_NDIM} dims, got {a.ndim}", field)
        if name in FLOAT_DTYPES and a.size and not finite(a):
            raise NonFiniteError("holds NaN or inf", field)
        return a

    def __post_init__(self) -> None:
        object.__setattr__(self, "_allowed", self.wire_dtypes)
        object.__setattr__(self, "_widen", dict(self.wire))
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


def empty_idx() -> Any:
    if np is None and not numpy_loaded():
        return WireArray("int64", (0,), b"")
    return np.zeros(0, dtype=np.int64)
