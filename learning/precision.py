"""`precision=bf16`: the PPO update's forward passes in bfloat16 under `torch.autocast`.

What stays float32: the weights (master copies), their gradients, the Adam state, the loss maths
after each network's output (every network returns float32: `networks`), and the acting forward.
Acting stays float32 because it is the deployed policy's computation (the local agents' and the
central server's numpy forward): the behaviour policy is what a robot runs, and `hammer up`
reproduces `hammer train` bit for bit in bf16 too (both learn through `TeamLearner.losses`).

bfloat16 pays only where the hardware multiplies it natively: x86 CPUs with AVX512_BF16 or AMX
(their /proc/cpuinfo flags), CUDA devices torch reports bf16 support on. Elsewhere torch emulates
it, many times slower than float32, so a run asking for it is refused up front (`check_precision`).
`HAMMER_ALLOW_EMULATED_BF16=1` lifts the refusal for numerics checks and tests on such hardware.
"""

from __future__ import annotations

import contextlib
import os

import torch

# CPU flags (/proc/cpuinfo) of native bfloat16 matrix multiplies.
NATIVE_BF16_FLAGS = ("avx512_bf16", "amx_bf16")
EMULATED_ENV = "HAMMER_ALLOW_EMULATED_BF16"


def bf16_unsupported(device: torch.device) -> str | None:
    """Why `device` has no native bfloat16 matmuls, or None when it has them."""
    if device.type == "cuda":
        if not torch.cuda.is_bf16_supported(including_emulation=False):
            return f"{torch.cuda.get_device_name(device)} has no native bfloat16"
        return None
    if device.type != "cpu":
        return f"device {device} is not cpu or cuda"
    from hammer.learning.host_info import cpu_info

    flags = cpu_info().get("simd_flags")
    if flags is None:
        return "this CPU's flags cannot be read (no /proc/cpuinfo)"
    if not any(f in flags for f in NATIVE_BF16_FLAGS):
        return f"this CPU has neither {' nor '.join(NATIVE_BF16_FLAGS)} (torch would emulate bfloat16, slower than float32)"
    return None


def check_precision(precision: str, device: torch.device) -> None:
    """Refuse `precision=bf16` on a device without native bfloat16, in one line naming the field
    and the fix (a ConfigError, as every refused config value)."""
    if precision != "bf16" or os.environ.get(EMULATED_ENV) == "1":
        return
    why = bf16_unsupported(device)
    if why is not None:
        from hammer.learning.config import ConfigError

        raise ConfigError(f"config field 'precision': precision=bf16 needs native bfloat16 matmuls and {why}; "
                          f"fix: --set precision=fp32 (or run on an AVX512_BF16/AMX CPU or a bf16 GPU)")


def update_autocast(precision: str, device: torch.device) -> contextlib.AbstractContextManager:
    """The context the PPO update's forward passes run in: bfloat16 autocast for bf16, nothing
    for fp32."""
    if precision == "bf16":
        return torch.autocast(device.type, dtype=torch.bfloat16)
    return contextlib.nullcontext()
