"""The field types messages are made of: wire dtypes, numpy array fields, names, size bounds.

An array travels as {"dtype", "shape", "data"} with raw little-endian bytes (never pickled); the
same check runs when a message is built in Python and when it is decoded, so a NaN or a wrong dtype
is caught at the sender as well as at the receiver.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np
from pydantic import AllowInfNan, Field, GetCoreSchemaHandler, GetJsonSchemaHandler, Strict
from pydantic_core import PydanticCustomError, core_schema

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
NAME_OF: dict[np.dtype, str] = {dt: name for name, dt in WIRE_DTYPES.items()}


def dtype_name(dt: np.dtype) -> str:
    """Wire name of a numpy dtype, or its numpy name when it is not on the whitelist."""
    name = NAME_OF.get(dt)
    if name is None:
        name = NAME_OF.get(dt.newbyteorder("<"), dt.name) if dt.byteorder == ">" else dt.name
    return name
MAX_NDIM = 8

MiB = 1 << 20
DEFAULT_MAX_BYTES = 4 * MiB
# Everything of a message but its array bytes, bounded: field names, ints, the type tag, run id
# (<= 64 chars), sender (<= 128) and up to four array maps ({"dtype", "shape" (<= 8 ints), "data"}).
HEADER_BYTES = 2048

NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
NAME_RULE = "1-64 chars of letters, digits, '_', '-', '.', starting with a letter or digit"


def field_error(reason: str, field: str | None, msg: str) -> PydanticCustomError:
    """A pydantic error whose type is a protocol `reason`; the codec maps it to a ProtocolError."""
    # The field name is in the text too: model-level errors have no `loc` in pydantic's message.
    return PydanticCustomError(reason, "{field}: {msg}" if field else "{msg}", {"msg": msg, "field": field or ""})


def check_name(value: str, what: str) -> str:
    """Validate a run id / role name used inside key expressions (raises ValueError)."""
    if not isinstance(value, str) or not NAME_RE.match(value):
        raise ValueError(f"invalid {what} {value!r}: use {NAME_RULE}")
    return value


def array_to_wire(a: np.ndarray) -> dict[str, Any]:
    """The wire map of an array: {"dtype": name, "shape": [..], "data": raw little-endian bytes}."""
    name = dtype_name(a.dtype)
    wire = WIRE_DTYPES.get(name)
    if wire is None:
        raise field_error("dtype", None, f"dtype {name} is not allowed on the wire ({', '.join(WIRE_DTYPES)})")
    if a.dtype.byteorder == ">":
        a = a.astype(wire)
    # tobytes() always writes C order, whatever the memory layout of `a`.
    return {"dtype": name, "shape": list(a.shape), "data": a.tobytes()}


def array_from_wire(d: dict, field: str | None) -> np.ndarray:
    if len(d) != 3 or "dtype" not in d or "shape" not in d or "data" not in d:
        raise field_error("field", field, f"array map must have exactly keys dtype, shape, data; got {sorted(d)}")
    name, shape, data = d["dtype"], d["shape"], d["data"]
    if not isinstance(name, str) or name not in WIRE_DTYPES:
        raise field_error("dtype", field, f"dtype {name!r} is not allowed ({', '.join(WIRE_DTYPES)})")
    if (
        not isinstance(shape, list)
        or len(shape) > MAX_NDIM
        or not all(type(n) is int and n >= 0 for n in shape)
    ):
        raise field_error("shape", field, f"shape must be a list of at most {MAX_NDIM} non-negative ints, got {shape!r}")
    if not isinstance(data, bytes):
        raise field_error("field", field, f"array data must be msgpack bin, got {type(data).__name__}")
    dtype = WIRE_DTYPES[name]
    count = 1
    for n in shape:
        count *= n
    if count * dtype.itemsize != len(data):
        raise field_error("shape", field, f"shape {shape} of {name} needs {count * dtype.itemsize} bytes, got {len(data)}")
    if name == "bool" and data and max(data) > 1:
        raise field_error("field", field, "bool array bytes must be 0 or 1")
    # astype(native, copy=True): decoded arrays are native-endian, writable and do not pin the buffer.
    return np.frombuffer(data, dtype=dtype).reshape(shape).astype(_NATIVE[name], copy=True)


@dataclass(frozen=True)
class ArrayField:
    """Pydantic annotation for an np.ndarray field with allowed dtypes and ranks."""

    dtypes: tuple[str, ...]
    ndims: tuple[int, ...] | None

    def validate(self, value: Any, info: core_schema.ValidationInfo) -> np.ndarray:
        field = info.field_name
        if isinstance(value, dict):
            a = array_from_wire(value, field)
        elif isinstance(value, np.ndarray):
            a = value
        else:
            raise field_error("field", field, f"expected a numpy array (or wire array map), got {type(value).__name__}")
        name = dtype_name(a.dtype)
        if name not in self.dtypes:
            hint = f"; cast with .astype(np.{self.dtypes[0]})" if self.dtypes[0] != "bool" else ""
            raise field_error("dtype", field, f"dtype {name} not allowed here, need one of {list(self.dtypes)}{hint}")
        if self.ndims is not None and a.ndim not in self.ndims:
            raise field_error("shape", field, f"needs {' or '.join(map(str, self.ndims))} dims, got shape {a.shape}")
        if a.ndim > MAX_NDIM:
            raise field_error("shape", field, f"at most {MAX_NDIM} dims, got {a.ndim}")
        if name in FLOAT_DTYPES and not np.isfinite(a).all():
            raise field_error("nonfinite", field, "holds NaN or inf")
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
    return Annotated[np.ndarray, ArrayField(dts, nds)]


NonNegInt = Annotated[int, Strict(), Field(ge=0)]
FiniteFloat = Annotated[float, Strict(), AllowInfNan(False)]
NonNegFloat = Annotated[float, Strict(), AllowInfNan(False), Field(ge=0)]
Name = Annotated[str, Strict(), Field(pattern=NAME_RE.pattern)]


def empty_idx() -> np.ndarray:
    return np.zeros(0, dtype=np.int64)
