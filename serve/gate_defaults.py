"""The default limits of a staged rollout (serve/canary.py's Gate), on their own so that `hammer push
--help` quotes them without loading pydantic: the help and the Gate read this one table."""

from __future__ import annotations

GATE_DEFAULTS: dict[str, int | float | str] = {
    "window_episodes": 100,
    "metric": "paper_metric",
    "metric_drop": 0.15,
    "metric_z": 2.0,
    "default_rate": 0.02,
    "fallback_rate": 0.05,
    "latency_ms": 20.0,
    "rejected": 0.0,
    "crashes": 0.0,
    "timeout_s": 600.0,
}
