"""What the machine-independent categorical draw costs (docs/learning.md "The randomness contract").

Per call, CPU time, median over alternating blocks (load from other processes hits both alike;
the load average is printed with the figures):
- numpy: `sampling.categorical_draw` (numpy's softmax, the exact softmax for rows near a CDF
  value) against the draw from numpy's softmax alone (`categorical_inverse_cdf(softmax(z), u)`,
  what it replaced), K rows of A = 5 logits;
- plain Python (the lite agent): `categorical.draw` (the exact exp) against the same inverse CDF on
  a softmax with `math.exp` (what it replaced), one row.

    .venv/bin/python benchmarks/bench_exact_draw.py [--blocks 15]
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time

import numpy as np


def _ab(old, new, n: int, blocks: int) -> tuple[float, float]:
    times: tuple[list[float], list[float]] = ([], [])
    for _ in range(blocks):
        for f, out in ((old, times[0]), (new, times[1])):
            t = time.process_time()
            for _ in range(n):
                f()
            out.append((time.process_time() - t) / n * 1e6)
    return statistics.median(times[0]), statistics.median(times[1])


def _libm_softmax(logits: list[float]) -> list[float]:
    """The plain-Python softmax with the platform's exp: the baseline measured against."""
    top = max(logits)
    e = [math.exp(v - top) for v in logits]
    s = 0.0
    for v in e:
        s += v
    return [v / s for v in e]


def main() -> None:
    from hammer.learning import categorical
    from hammer.learning.numpy_policy import softmax
    from hammer.learning.sampling import categorical_draw, categorical_inverse_cdf

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--blocks", type=int, default=15)
    blocks = ap.parse_args().blocks
    rng = np.random.default_rng(0)
    print(f"load {' '.join(f'{x:.2f}' for x in os.getloadavg())}; CPU µs per call, median of {blocks} blocks")
    print("path                         K   library exp   exact draw   difference")
    for k in (1, 32, 1024):
        z = (rng.standard_normal((k, 5)) * 2).astype(np.float32)
        u = rng.random(k)
        old, new = _ab(lambda z=z, u=u: categorical_inverse_cdf(softmax(z), u), lambda z=z, u=u: categorical_draw(z, u),
                       2000 // k + 20, blocks)
        print(f"numpy (trainer, numpy agent) {k:<4}{old:>10.1f}{new:>13.1f}{new - old:>+12.1f}")
    row = (rng.standard_normal(5) * 2).tolist()
    old, new = _ab(lambda: categorical.categorical_inverse_cdf(_libm_softmax(row), 0.37),
                   lambda: categorical.draw(row, 0.37), 5000, blocks)
    print(f"plain Python (lite agent)    1   {old:>10.2f}{new:>13.2f}{new - old:>+12.2f}")
    print(f"load {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
