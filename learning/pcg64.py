"""numpy's PCG64 and SeedSequence in pure Python: the lite edge agent's random stream, draw for draw.

Why: the randomness contract (learning/sampling.py) gives every local agent the stream
`np.random.default_rng([seed, LOCAL_STREAM, agent])` and a discrete agent draws one uniform per
env copy and step (`rng.random(K)`). The edge agent of a discrete K=1 team runs without numpy
(numpy and numpy.random are a large share of its memory budget, docs/deploy.md "Footprint"), so it needs the
same numbers without numpy: this is the same integer maths (numpy/random/bit_generator.pyx
SeedSequence, numpy/random/src/pcg64 with the 128-bit default multiplier and XSL-RR output) and
numpy's uniform double ((next64 >> 11) * 2**-53). tests/test_lite_acting.py checks it against numpy.
"""

from __future__ import annotations

from collections.abc import Iterable

_M32, _M64, _M128 = (1 << 32) - 1, (1 << 64) - 1, (1 << 128) - 1
# SeedSequence's hash constants (numpy/random/bit_generator.pyx).
_INIT_A, _MULT_A, _INIT_B, _MULT_B = 0x43B0D7E5, 0x931E8875, 0x8B51F9DD, 0x58F38DED
_MIX_L, _MIX_R, _XSHIFT, _POOL = 0xCA01F9DD, 0x4973F715, 16, 4
_PCG_MULT = 0x2360ED051FC65DA44385DF649FCCF645  # PCG_DEFAULT_MULTIPLIER_128
_TWO_M53 = 1.0 / 9007199254740992.0
LOCAL_STREAM = 1  # learning.sampling.LOCAL_STREAM (that module imports numpy; tests/test_lite_acting.py checks they agree)


def _words(n: int) -> list[int]:
    """An entropy int as numpy's `_int_to_uint32_array`: its 32-bit words, least significant first."""
    if n < 0:
        raise ValueError("expected non-negative integer")
    out = [n & _M32] if n == 0 else []
    while n > 0:
        out.append(n & _M32)
        n >>= 32
    return out


def seed_sequence_state(entropy: int | Iterable[int], n_words64: int) -> list[int]:
    """`np.random.SeedSequence(entropy).generate_state(n_words64, np.uint64)` as Python ints."""
    ent = _words(entropy) if isinstance(entropy, int) else [w for e in entropy for w in _words(int(e))]
    hash_const = _INIT_A

    def hashmix(value: int) -> int:
        nonlocal hash_const
        value = (value ^ hash_const) & _M32
        hash_const = (hash_const * _MULT_A) & _M32
        value = (value * hash_const) & _M32
        return value ^ (value >> _XSHIFT)

    def mix(x: int, y: int) -> int:
        r = (_MIX_L * x - _MIX_R * y) & _M32
        return r ^ (r >> _XSHIFT)

    pool = [hashmix(ent[i] if i < len(ent) else 0) for i in range(_POOL)]
    for src in range(_POOL):
        for dst in range(_POOL):
            if src != dst:
                pool[dst] = mix(pool[dst], hashmix(pool[src]))
    for src in range(_POOL, len(ent)):
        for dst in range(_POOL):
            pool[dst] = mix(pool[dst], hashmix(ent[src]))
    out32, h = [], _INIT_B
    for i in range(2 * n_words64):
        v = (pool[i % _POOL] ^ h) & _M32
        h = (h * _MULT_B) & _M32
        v = (v * h) & _M32
        out32.append(v ^ (v >> _XSHIFT))
    return [out32[2 * i] | (out32[2 * i + 1] << 32) for i in range(n_words64)]


class PCG64:
    """numpy's PCG64 bit generator seeded from a SeedSequence of `entropy`, with the one draw a
    discrete local agent makes: `random(k)`, k uniform doubles in [0, 1) as `Generator.random(k)`."""

    __slots__ = ("inc", "state")

    def __init__(self, entropy: int | Iterable[int]) -> None:
        s0, s1, i0, i1 = seed_sequence_state(entropy, 4)
        initstate, initseq = (s0 << 64) | s1, (i0 << 64) | i1
        self.inc = ((initseq << 1) | 1) & _M128
        self.state = 0
        self._step()
        self.state = (self.state + initstate) & _M128
        self._step()

    def _step(self) -> None:
        self.state = (self.state * _PCG_MULT + self.inc) & _M128

    def next64(self) -> int:
        """The next 64-bit output (XSL-RR of the stepped state)."""
        self.state = s = (self.state * _PCG_MULT + self.inc) & _M128
        x = ((s >> 64) ^ s) & _M64
        r = s >> 122
        return ((x >> r) | (x << (64 - r))) & _M64

    def random(self, k: int) -> list[float]:
        return [(self.next64() >> 11) * _TWO_M53 for _ in range(k)]


def lite_stream(seed: int, stream_id: int, index: int = 0) -> PCG64:
    """`learning.sampling.stream(seed, stream_id, index)` without numpy (same draws of `random`)."""
    return PCG64([seed, stream_id, index])

