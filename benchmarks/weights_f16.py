"""What sending the weights as float16 (`--runtime weights_float16=true`) changes: bytes and actions.

    python -m hammer.benchmarks.weights_f16 BUNDLE [--episodes 200] [--out FILE.json]

Serves the bundle twice with `hammer serve` (same seed, `trace=true`): with the weights as exported
(float32) and as float16 on the wire. The agents compute in float32 either way, so any difference is
the rounding of the weights. Prints the weights' bytes both ways (and a general compressor's, for
comparison), the share of actions that differ step for step, the largest difference in the central
messages, and the paper metric of both runs. A served run is deterministic for a seed (its fallback
never fires without faults), so every difference is the float16 weights'.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
from hammer.benchmarks.results import write_json


def _serve(bundle: Path, run: Path, episodes: int, float16: bool) -> dict:
    cmd = [sys.executable, "-P", "-m", "hammer.cli", "serve", str(bundle), "--episodes", str(episodes),
           "--run-dir", str(run), "--no-dashboard", "--runtime", "trace=true",
           *(["--runtime", "weights_float16=true"] if float16 else [])]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=1800, check=False)
    if r.returncode != 0:
        raise RuntimeError(f"hammer serve failed ({r.returncode}): {r.stderr[-1500:]}")
    trace = np.load(run / "trace.npz")
    summary = json.loads((run / "summary.json").read_text())
    return {"trace": {k: trace[k] for k in trace.files}, "summary": summary}


def compare(bundle: Path, work: Path, episodes: int) -> dict:
    from hammer.learning.numpy_policy import float16_blob

    sizes = {}
    for name in ("local.safetensors", "central.safetensors"):
        f = bundle / name
        if f.is_file():
            blob = f.read_bytes()
            sizes[name] = {"float32": len(blob), "float16": len(float16_blob(blob)),
                           "zlib9_float32": len(zlib.compress(blob, 9))}
    a = _serve(bundle, work / "float32", episodes, False)
    b = _serve(bundle, work / "float16", episodes, True)
    ta, tb = a["trace"], b["trace"]
    n = min(len(ta["steps"]), len(tb["steps"]))
    if not np.array_equal(ta["steps"][:n], tb["steps"][:n]):
        raise RuntimeError("the two traces hold different steps (trace_max_mb reached?); fix: fewer --episodes")
    acts_a, acts_b = ta["actions"][:n], tb["actions"][:n]
    differ = acts_a != acts_b if acts_a.dtype.kind in "iu" else ~np.isclose(acts_a, acts_b, atol=1e-6)
    first = int(np.argmax(differ.reshape(n, -1).any(axis=1))) if differ.any() else None
    msgs = np.abs(ta["msgs"][:n].astype(np.float64) - tb["msgs"][:n]).max() if "msgs" in ta else None

    def metric(s: dict) -> float | None:
        return s.get("final_paper_metric_last500", s.get("paper_metric_mean"))

    return {"bundle": str(bundle), "episodes": episodes, "steps": n, "weights_bytes": sizes,
            "actions_differing_share": float(differ.mean()), "first_step_differing": first,
            "max_message_difference": None if msgs is None else float(msgs),
            "paper_metric": {"float32": metric(a["summary"]), "float16": metric(b["summary"])},
            "defaults": {"float32": a["summary"].get("links", {}).get("default_actions"),
                         "float16": b["summary"].get("links", {}).get("default_actions")}}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m hammer.benchmarks.weights_f16", description=__doc__.split("\n\n")[0])
    ap.add_argument("bundle", type=Path)
    ap.add_argument("--episodes", type=int, default=200)
    ap.add_argument("--work", type=Path, default=Path("/tmp/hammer-bench-f16"))
    ap.add_argument("--out", type=Path)
    a = ap.parse_args(argv)
    a.work.mkdir(parents=True, exist_ok=True)
    r = compare(a.bundle, a.work, a.episodes)
    for name, s in r["weights_bytes"].items():
        print(f"{name}: {s['float32']:,} B as float32, {s['float16']:,} B as float16 "
              f"({s['float16'] / s['float32']:.2f}x), {s['zlib9_float32']:,} B float32 zlib -9")
    print(f"{r['steps']} steps x K x N actions: {100 * r['actions_differing_share']:.3f} % differ "
          f"(first at step {r['first_step_differing']}); largest message difference {r['max_message_difference']}; "
          f"paper metric float32 {r['paper_metric']['float32']} vs float16 {r['paper_metric']['float16']}; "
          f"defaults {r['defaults']}")
    write_json(a.out, r)
    return 0


if __name__ == "__main__":
    sys.exit(main())
