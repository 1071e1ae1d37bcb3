"""The env host's trace (`--runtime trace=true`): what every step carried, to replay a run exactly.

Kept in memory to the end, the trace grew by every step's observations, messages and actions
until the run ended or the machine ran out. So the steps go to disk in segments
(`RUN/trace/seg-<first step>.npz`, at most `SEGMENT_BYTES` each, one held in memory), the oldest
segments are deleted while all of them take more than `max_bytes`, and at the end the segments are
joined into `trace.npz` one array and one segment at a time. trace.npz is what it always was
(arrays of TRACE_ARRAYS, one row per step, in order); once the cap was reached it holds the latest
steps only, and its `steps` say which. The disk holds the cap, twice while trace.npz is joined.
"""

from __future__ import annotations

import logging
import shutil
import zipfile
from collections import deque
from pathlib import Path

import numpy as np

TRACE_ARRAYS = ("steps", "obs", "msgs", "actions", "fallback", "defaulted", "versions")
TRACE_DIR = "trace"
SEGMENT_BYTES = 8 * 2**20

log = logging.getLogger("hammer.env")


class TraceWriter:
    def __init__(self, run_dir: Path, max_bytes: int, segment_bytes: int = SEGMENT_BYTES) -> None:
        self.dir = Path(run_dir) / TRACE_DIR
        self.out = Path(run_dir) / "trace.npz"
        shutil.rmtree(self.dir, ignore_errors=True)  # an earlier session's segments are not this run's
        self.out.unlink(missing_ok=True)
        self.max_bytes, self.segment_bytes = max(1, int(max_bytes)), max(1, int(segment_bytes))
        self.buf: dict[str, np.ndarray] | None = None
        self.n = 0  # steps in buf
        self.segments: deque[tuple[Path, int, int]] = deque()  # (file, bytes, steps), oldest first
        self.disk = 0
        self.steps = 0  # every step added
        self.dropped_steps = 0

    def add(self, *values) -> None:
        """One step: a value per TRACE_ARRAYS name, in that order (copied)."""
        if self.buf is None:
            row = [np.asarray(v) for v in values]
            per_step = max(1, sum(a.nbytes for a in row))
            rows = max(1, min(self.segment_bytes, self.max_bytes) // per_step)
            self.buf = {name: np.empty((rows, *a.shape), a.dtype) for name, a in zip(TRACE_ARRAYS, row, strict=True)}
        for name, v in zip(TRACE_ARRAYS, values, strict=True):
            self.buf[name][self.n] = v
        self.n += 1
        self.steps += 1
        if self.n == len(self.buf["steps"]):
            self._write_segment()

    def _write_segment(self) -> None:
        if not self.n:
            return
        self.dir.mkdir(exist_ok=True)
        path = self.dir / f"seg-{int(self.buf['steps'][0]):012d}.npz"
        np.savez(path, **{k: v[:self.n] for k, v in self.buf.items()})
        size = path.stat().st_size
        self.segments.append((path, size, self.n))
        self.disk += size
        self.n = 0
        while self.disk > self.max_bytes and len(self.segments) > 1:
            old, old_size, old_steps = self.segments.popleft()
            old.unlink(missing_ok=True)
            self.disk -= old_size
            if not self.dropped_steps:
                log.warning("trace over trace_max_mb (%.0f MB): dropping its oldest steps; trace.npz keeps the latest",
                            self.max_bytes / 2**20)
            self.dropped_steps += old_steps

    def close(self) -> Path | None:
        """Join the segments into trace.npz (None if no step was traced) and delete them."""
        self._write_segment()
        if not self.segments:
            return None
        first = np.load(self.segments[0][0])
        total = sum(s for _, _, s in self.segments)
        tmp = self.out.with_suffix(".npz.tmp")
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
            for name in TRACE_ARRAYS:
                a = first[name]
                header = {"descr": np.lib.format.dtype_to_descr(a.dtype), "fortran_order": False,
                          "shape": (total, *a.shape[1:])}
                with zf.open(f"{name}.npy", "w", force_zip64=True) as f:
                    np.lib.format.write_array_header_1_0(f, header)
                    for path, _, _ in self.segments:
                        with np.load(path) as seg:
                            f.write(np.ascontiguousarray(seg[name]).tobytes())
        first.close()
        tmp.replace(self.out)
        shutil.rmtree(self.dir, ignore_errors=True)
        return self.out
