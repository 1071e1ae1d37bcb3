"""What every env module shares: the error for an env that cannot be built, and the plain-data
description a worker process rebuilds its env from (never a pickled env).

A module of its own so that the registry, the PettingZoo adapter and the subprocess workers can
all import it without importing each other.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


class EnvConfigError(ValueError):
    """An env name, a kwarg or a size that the registry cannot build; the message says the fix."""


@dataclass(frozen=True)
class EnvDescription:
    """Everything needed to rebuild an env in another process: plain, picklable data only."""

    name: str
    n_agents: int
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    adapters: tuple[str, ...] = ()  # envs.adapters names, applied to each parallel env built

