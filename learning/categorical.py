"""The categorical draw of the randomness contract, the same on every machine, in plain Python.

A local agent draws its action by inverse CDF on the float64 softmax of its logits
(`learning.sampling`). The softmax needs exp, and no exp a library provides is the same
everywhere: numpy's float64 exp takes a SIMD path on CPUs with AVX-512 and glibc's on the others,
glibc's own exp takes an FMA path or a plain one by the CPU, and another libc (a robot's) has its
own. They differ in the last bit for a few percent of inputs, so a uniform that falls between two
CDFs computed with two exps is drawn as two different actions. `exp_nonpositive` below is built
from +, -, *, / alone, which IEEE 754 rounds the same on every machine, in plain Python and in
numpy alike; the exact softmax sums in index order, as `cumsum` does.

Every draw is defined as `draw(logits, u)`: the inverse CDF on this exact softmax. The lite agent
computes it directly (a handful of logits, plain Python either way). Numpy callers
(`sampling.categorical_draw`) compute the softmax with numpy's fast exp and fall back to `draw`
for a row whose uniform lies within `MARGIN` of one of its CDF values: any exp within a few ulps
of the true value keeps the CDF far closer than that to the exact one (see `MARGIN`), so outside
the margin the fast draw is the exact draw, and inside it the exact draw is computed. Either way
the action is `draw(logits, u)`, whichever CPU, BLAS, libc or numpy build computed it.

No numpy here: the lite edge agent imports this module (docs/deploy.md "Footprint").
"""

from __future__ import annotations

import math

# exp(r) on |r| <= ln2/2 as 1 + 2r/(R(r^2) - r), the rational form of fdlibm's e_exp.c (< 1 ulp).
_INV_LN2 = 1.44269504088896338700e+00
_LN2_HI = 6.93147180369123816490e-01  # trailing 32 bits zero: k * _LN2_HI is exact for |k| < 2^20
_LN2_LO = 1.90821492927058770002e-10
_P1 = 1.66666666666666019037e-01
_P2 = -2.77777777770155933842e-03
_P3 = 6.61375632143793436117e-05
_P4 = -1.65339022054652515390e-06
_P5 = 4.13813679705723846039e-08
_ROUND = 6755399441055744.0  # 1.5 * 2^52: (v + _ROUND) - _ROUND is v rounded to the nearest integer (ties to even)
_LOW = -746.0  # exp of anything below rounds to 0 (the least subnormal is 2^-1074, about e^-744.4)
_TWO_M64 = 2.0 ** -64

# How far a uniform must lie from every CDF value of its row for a draw from a fast softmax to be
# the exact draw. With A actions, an exp within E ulps and float64 sums, a fast CDF value lies
# within about (2E + 3A + 4) * 2^-52 of the exact one: below 1e-11 for E = 16 and A = 10,000.
# 2^-30 (9.3e-10) leaves a factor of 100 on that; a uniform falls inside it with probability
# about 2A * 2^-30 per draw (1e-8 for 5 actions), when the row is computed exactly.
MARGIN = 2.0 ** -30


def exp_nonpositive(x: float) -> float:
    """e^x for x <= 0 (what a softmax needs after subtracting the row's maximum), within 1 ulp,
    from +, -, *, / only; nan stays nan. Positive x is outside its range (it would overflow the
    scaling below)."""
    if math.isnan(x):
        return x
    x = max(x, _LOW)
    k = (x * _INV_LN2 + _ROUND) - _ROUND
    hi = x - k * _LN2_HI
    lo = k * _LN2_LO
    r = hi - lo
    rr = r * r
    c = r - rr * (_P1 + rr * (_P2 + rr * (_P3 + rr * (_P4 + rr * _P5))))
    y = 1.0 - ((lo - (r * c) / (2.0 - c)) - hi)
    # 2^k in two exact steps: y * 2^(k+64) is a normal number, and the one rounding of the last
    # product is IEEE's (also into the subnormals, where a direct ldexp would rely on the libc).
    return (y * math.ldexp(1.0, int(k) + 64)) * _TWO_M64


def softmax(logits: list[float]) -> list[float]:
    """The exact float64 softmax of one row: the maximum subtracted, `exp_nonpositive`, the sum in
    index order."""
    top = max(logits)
    e = [exp_nonpositive(v - top) for v in logits]
    s = 0.0
    for v in e:
        s += v
    return [v / s for v in e]


def categorical_inverse_cdf(probs: list[float], u: float) -> int:
    """`sampling.categorical_inverse_cdf` of one row: index a with cdf[a-1] <= u < cdf[a]."""
    c, idx = 0.0, 0
    for p in probs:
        c += p
        idx += c <= u
    return min(idx, len(probs) - 1)


def draw(logits: list[float], u: float) -> int:
    """The action of the randomness contract for one row of logits and its uniform u in [0, 1)."""
    return categorical_inverse_cdf(softmax(logits), u)
