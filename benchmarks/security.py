"""What the secure profile costs: the same short run plain and secure, in one process, alternated.

Each repeat runs the plain profile and then the secure one (same config, same seed), so both see
the same host load; the figures are the env host's own (env-steps/s over the whole run including
PPO updates, and the latency of one distributed step: observations out -> every action back,
p50/p99). Medians over the repeats. The two profiles must produce the same metrics.csv (the
secure profile changes who may talk, not what is said), and the table says whether they did.
"""

from __future__ import annotations

import csv
import os
import statistics
import tempfile
import time
from pathlib import Path

PROFILES = ("plain", "secure")
FIGURES = ("env_steps_per_s", "step_latency_ms_p50", "step_latency_ms_p99")


def _metrics(run_dir: Path) -> list[dict[str, str]]:
    with open(run_dir / "metrics.csv", newline="") as f:
        return [{k: v for k, v in r.items() if k != "wall_time"} for r in csv.DictReader(f)]


def bench_security(preset: str = "cn3", episodes: int = 100, repeats: int = 2) -> dict:
    """{"runs": [one dict per run], "median": {profile: {figure: value}}, "same_metrics": bool,
    "secure_over_plain": {figure: ratio}}."""
    from deploy.settings import RuntimeSettings
    from deploy.up import launch
    from learning.config import merge_config

    cfg = merge_config(preset, overrides=[f"episodes={episodes}", "variant=hammer"])
    runs, same, load0 = [], True, os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="hammer-bench-security-") as tmp:
        for r in range(repeats):
            dirs = {}
            for profile in PROFILES:
                # a loaded host can take more than the default minute to start every role: no figure depends on it
                settings = RuntimeSettings(run_id=f"bsec-{profile}-{r}-{os.getpid()}", secure=profile == "secure",
                                           startup_timeout_s=300)
                dirs[profile] = Path(tmp) / f"{profile}-{r}"
                res = launch(cfg, settings, dirs[profile])
                links = res.summary.get("links", {})
                runs.append({"profile": profile, "repeat": r, **{f: res.summary[f] for f in FIGURES},
                             "default_actions": links.get("default_actions"),
                             "msg_fallback_copies": links.get("msg_fallback_copies"), "wall_s": res.wall_time,
                             "loadavg_1m_end": os.getloadavg()[0]})
            same = same and _metrics(dirs["plain"]) == _metrics(dirs["secure"])
    median = {p: {f: statistics.median(x[f] for x in runs if x["profile"] == p) for f in FIGURES} for p in PROFILES}
    ratio = {f: median["secure"][f] / median["plain"][f] for f in FIGURES}
    return {"preset": preset, "episodes": episodes, "repeats": repeats, "runs": runs, "median": median,
            "secure_over_plain": ratio, "same_metrics": same, "loadavg_1m_start": load0,
            "loadavg_1m": os.getloadavg()[0], "cpu_count": os.cpu_count(),
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
