"""A compact, committable record of a set of runs: config, final figures and a downsampled curve.

Run directories are large (per-episode CSVs, checkpoints) and stay out of git; this JSON keeps
what a reader needs to check the published tables and figures.
"""

from __future__ import annotations

import json
from pathlib import Path

from hammer.experiments.runs import Run, rolling_mean


def export_runs(runs: list[Run], out: Path, window: int = 500, every: int = 250) -> None:
    records = []
    for r in runs:
        curve = rolling_mean(r.paper_metric, window)
        summary = json.loads((r.path / "summary.json").read_text()) if r.finished else {}
        records.append({
            "run": r.path.name, "setting": r.setting, "label": r.label, "seed": r.seed,
            "config": {k: r.config.get(k) for k in ("env", "n_agents", "variant", "central_mode", "msg_dim",
                                                   "num_envs", "rollout_steps", "episodes", "seed")},
            "episodes": len(r.paper_metric), "finished": r.finished,
            "final_paper_metric_last500": float(r.paper_metric[-500:].mean()) if len(r.paper_metric) else None,
            "final_team_return_last500": float(r.team_return[-500:].mean()) if len(r.team_return) else None,
            "wall_time_s": summary.get("wall_time"), "env_steps_per_s": summary.get("env_steps_per_s_this_session"),
            f"rolling{window}_every{every}": [round(float(v), 3) for v in curve[every - 1::every]],
        })
    Path(out).write_text(json.dumps(records, indent=1))
