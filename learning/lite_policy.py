"""The local policy of a discrete MLP team in pure Python: the lite edge agent's forward.

Why: numpy is a large share of the edge agent's memory budget (docs/deploy.md "Footprint"); a robot
acting on one env copy (K=1) with a discrete MLP policy needs a few thousand multiply-adds per step,
which plain Python does in well under a millisecond. What numpy_policy.py and sampling.py do, here
without numpy:
- the weights: a safetensors blob parsed directly (8-byte little-endian header length, a JSON
  header, raw little-endian tensors; never pickle), every check safetensors makes that matters
  here (offsets inside the data, byte counts, the dtypes a policy holds), float16 read as float32;
- the forward: x W^T + b with tanh between layers, each value rounded to float32 as numpy's
  float32 maths keeps them (numpy's BLAS sums in float32 in its own order, so a logit may differ
  in its last bits: the action differs only when a uniform falls within that of a class boundary,
  measured in docs/deploy.md "Footprint");
- the draw: `learning.categorical.draw`, the contract's exact softmax and inverse CDF, which
  the numpy agent's draw (`sampling.categorical_draw`) equals on every machine.

What it cannot run (a continuous policy, a conv encoder) is refused by `lite_supported`; the edge
agent then takes the numpy path (serve/edge_entry.py).
"""

from __future__ import annotations

import json
import math
import struct
import sys
from array import array
from operator import mul

_TYPES = {"F32": ("f", 4), "F16": ("e", 2), "F64": ("d", 8)}
MAX_HEADER = 100 * 1024 * 1024  # what safetensors itself accepts


class LiteWeightsError(ValueError):
    """A weights blob this module cannot read (malformed, or a network it does not run)."""


def read_safetensors(blob: bytes) -> dict[str, tuple[tuple[int, ...], list[float]]]:
    """name -> (shape, flat values as Python floats, float32-exact) of a safetensors blob of float tensors."""
    if len(blob) < 8:
        raise LiteWeightsError("safetensors: shorter than its 8-byte header length")
    (n,) = struct.unpack_from("<Q", blob, 0)
    if n > MAX_HEADER or 8 + n > len(blob):
        raise LiteWeightsError(f"safetensors: header length {n} beyond the blob ({len(blob)} bytes)")
    try:
        header = json.loads(bytes(blob[8:8 + n]).decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as e:
        raise LiteWeightsError(f"safetensors: header is not JSON: {e}") from None
    if type(header) is not dict:
        raise LiteWeightsError("safetensors: header is not a map")
    data = memoryview(blob)[8 + n:]
    out = {}
    for name, t in header.items():
        if name == "__metadata__":
            continue
        if type(t) is not dict or set(t) != {"dtype", "shape", "data_offsets"}:
            raise LiteWeightsError(f"safetensors: tensor {name!r} is not {{dtype, shape, data_offsets}}")
        dtype, shape, offsets = t["dtype"], t["shape"], t["data_offsets"]
        if dtype not in _TYPES:
            raise LiteWeightsError(f"safetensors: tensor {name!r} is {dtype}; the lite policy reads {sorted(_TYPES)}")
        if (type(shape) is not list or not all(type(d) is int and d >= 0 for d in shape) or type(offsets) is not list
                or len(offsets) != 2 or not all(type(o) is int for o in offsets)):
            raise LiteWeightsError(f"safetensors: tensor {name!r} has a malformed shape or offsets")
        code, size = _TYPES[dtype]
        begin, end = offsets
        if not 0 <= begin <= end <= len(data) or end - begin != size * math.prod(shape):
            raise LiteWeightsError(f"safetensors: tensor {name!r} offsets {offsets} do not hold {dtype} {shape}")
        raw = data[begin:end]
        if code == "e":
            values = list(struct.unpack(f"<{len(raw) // 2}e", raw))
        else:
            a = array(code)
            a.frombytes(raw)
            if sys.byteorder != "little":  # pragma: no cover - big-endian hosts
                a.byteswap()
            values = a.tolist() if code == "f" else array("f", a).tolist()  # float64 -> float32, as astype
        out[name] = (tuple(shape), values)
    return out


def safetensors_shapes(path) -> dict[str, tuple[int, ...]]:
    """Tensor name -> shape of a safetensors file, from its header only (never the payload, never
    pickle, no numpy: what `lite_supported` and a bundle's check need, serve/bundle.py)."""
    with open(path, "rb") as f:
        head = f.read(8)
        if len(head) < 8:
            raise LiteWeightsError("shorter than its 8-byte header length")
        (n,) = struct.unpack("<Q", head)
        if n > MAX_HEADER:
            raise LiteWeightsError(f"header length {n} over {MAX_HEADER}")
        raw = f.read(n)
    try:
        header = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as e:
        raise LiteWeightsError(f"header is not JSON: {e}") from None
    if type(header) is not dict:
        raise LiteWeightsError("header is not a map")
    out = {}
    for name, t in header.items():
        if name == "__metadata__":
            continue
        shape = t.get("shape") if type(t) is dict else None
        if type(shape) is not list or not all(type(d) is int and d >= 0 for d in shape) or "dtype" not in t \
                or "data_offsets" not in t:
            raise LiteWeightsError(f"tensor {name!r} is not {{dtype, shape, data_offsets}}")
        out[name] = tuple(shape)
    return out


def safetensors_names(path) -> set[str]:
    """The tensor names of a safetensors file, from its header only."""
    return set(safetensors_shapes(path))


def f32(values: list[float]) -> list[float]:
    """Each value rounded to float32 (round to nearest even, as numpy's float32 results are)."""
    return array("f", values).tolist()


def lite_supported(names: set[str] | dict) -> str | None:
    """None when the lite policy runs a local policy with these tensors, else why not."""
    if "log_std" in names:
        return "continuous actions"
    if any(k.startswith(("actor_enc.", "critic_enc.")) for k in names):
        return "a conv encoder"
    if "actor.layers.0.weight" not in names:
        return "no actor.layers.0.weight"
    return None


class LiteLocalPolicy:
    """The actor of `numpy_policy.NumpyLocalPolicy` for a discrete MLP team (the critic is not needed to act)."""

    def __init__(self, blob: bytes) -> None:
        tensors = read_safetensors(blob)
        why = lite_supported(tensors)
        if why is not None:
            raise LiteWeightsError(f"the lite policy does not run this network ({why})")
        self.layers: list[tuple[list[list[float]], list[float]]] = []
        i = 0
        while f"actor.layers.{i}.weight" in tensors:
            (rows, cols), w = tensors[f"actor.layers.{i}.weight"]
            bshape, b = tensors.get(f"actor.layers.{i}.bias", ((None,), None))
            if b is None or bshape != (rows,) or (self.layers and cols != len(self.layers[-1][1])):
                raise LiteWeightsError(f"actor.layers.{i}: weight {rows}x{cols} and its bias {bshape} do not chain")
            self.layers.append(([w[r * cols:(r + 1) * cols] for r in range(rows)], b))
            i += 1
        self.in_dim = len(self.layers[0][0][0]) if self.layers[0][0] else 0
        self.n_actions = len(self.layers[-1][1])

    def logits(self, x: list[float]) -> list[float]:
        """x W^T + b per layer, tanh between layers, every value a float32 as numpy's forward keeps it."""
        if len(x) != self.in_dim:
            raise ValueError(f"the policy takes {self.in_dim} inputs, got {len(x)}")
        last = len(self.layers) - 1
        for i, (w, b) in enumerate(self.layers):
            z = f32([sum(map(mul, row, x)) for row in w])
            x = f32([v + c for v, c in zip(z, b)])
            if i < last:
                x = f32([math.tanh(v) for v in x])
        return x
