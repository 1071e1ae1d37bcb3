"""What the numbers of a run depend on besides its config and seed: the CPU path of the maths.

A run reproduces bit for bit on the same machine, but the same config on another host can diverge
after a thousand episodes because torch (oneDNN, MKL) and numpy (OpenBLAS) pick their kernels by
the CPU's instruction sets and by the thread count, and different kernels round differently
(docs/learning.md, "Determinism"). Every run's summary therefore records that path, so a difference
between two runs can be traced to code, config or machine.

Only what is already loaded is described: torch is reported only if this process imported it (the
env host and the central agent never do), so collecting this never costs an import.
"""

from __future__ import annotations

import os
import platform
import re
import sys
from pathlib import Path
from typing import Any

# CPU flags that decide which SIMD kernels the libraries may dispatch to.
_SIMD_FLAG = re.compile(r"^(sse\d.*|ssse3|avx.*|amx.*|fma.?|f16c|bmi\d|vnni.*)$")
# Environment variables that change the maths libraries' thread counts or kernel choice.
_ENV_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "OPENBLAS_CORETYPE", "MKL_CBWR",
             "MKL_ENABLE_INSTRUCTIONS",
             "ATEN_CPU_CAPABILITY", "DNNL_MAX_CPU_ISA", "ONEDNN_MAX_CPU_ISA", "DNNL_DEFAULT_FPMATH_MODE",
             "KMP_AFFINITY", "KMP_DETERMINISTIC_REDUCTION", "TORCHINDUCTOR_FREEZING")


def cpu_info(cpuinfo: Path = Path("/proc/cpuinfo")) -> dict[str, Any]:
    """Model name, vendor, family/model/stepping, SIMD flags (sorted) and logical CPU count."""
    out: dict[str, Any] = {"machine": platform.machine(), "logical_cpus": os.cpu_count()}
    try:
        text = cpuinfo.read_text()
    except OSError:  # not Linux: the platform string is all there is
        out["model"] = platform.processor() or None
        return out
    first = text.split("\n\n", 1)[0]
    fields = dict(line.split(":", 1) for line in first.splitlines() if ":" in line)
    fields = {k.strip(): v.strip() for k, v in fields.items()}
    out.update(model=fields.get("model name"), vendor=fields.get("vendor_id"),
               family_model_stepping=[fields.get("cpu family"), fields.get("model"), fields.get("stepping")],
               microcode=fields.get("microcode"))
    flags = fields.get("flags", "").split()
    out["simd_flags"] = sorted(f for f in flags if _SIMD_FLAG.match(f))
    return out


def numpy_blas() -> dict[str, Any]:
    """numpy's BLAS/LAPACK as built (name, version, configuration line)."""
    import numpy as np

    out: dict[str, Any] = {"version": np.__version__}
    try:
        deps = np.show_config(mode="dicts").get("Build Dependencies", {})
    except (TypeError, AttributeError):  # numpy < 1.26 has no dict mode
        return out
    for key in ("blas", "lapack"):
        d = deps.get(key, {})
        out[key] = {k: d.get(k) for k in ("name", "version", "openblas configuration") if d.get(k)}
    return out


def torch_info() -> dict[str, Any] | None:
    """torch's version, CPU dispatch level, MKL / oneDNN versions and thread settings; None if this
    process has not imported torch."""
    torch = sys.modules.get("torch")
    if torch is None:
        return None
    config = torch.__config__.show()

    def find(pattern: str) -> str | None:
        m = re.search(pattern, config)
        return m.group(1).strip() if m else None

    return {
        "version": torch.__version__,
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "mkl": find(r"Math Kernel Library Version ([^\n]+?) for"),
        "onednn": find(r"(?:MKL-DNN|oneDNN) (v[\d.]+)"),
        "mkldnn_enabled": bool(torch.backends.mkldnn.is_available() and torch.backends.mkldnn.enabled),
        "num_threads": torch.get_num_threads(),
        "num_interop_threads": torch.get_num_interop_threads(),
        "deterministic_algorithms": torch.are_deterministic_algorithms_enabled(),
    }


def host_info() -> dict[str, Any]:
    """Everything above, plus Python and the relevant environment variables (unset ones omitted)."""
    return {
        "python": platform.python_version(),
        "os": platform.platform(),
        "cpu": cpu_info(),
        "numpy": numpy_blas(),
        "torch": torch_info(),
        "env": {k: os.environ[k] for k in _ENV_VARS if k in os.environ},
    }
