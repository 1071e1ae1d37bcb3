"""The lightweight roles: local agents and the central server of a real `hammer up` run never load torch
(the central acts with a numpy forward), nor does the env host: only the learner holds torch (which
also shows the check can see torch in a process that has it)."""

from __future__ import annotations

import psutil
from hammer.deploy.launcher import launch
from hammer.learning.config import merge_config
from hammer.runtime.settings import RuntimeSettings


def _maps_torch(pid: int) -> bool:
    return any("libtorch" in m.path for m in psutil.Process(pid).memory_maps())


def test_only_the_learner_runs_torch(tmp_path):
    cfg = merge_config("cn3", overrides=["episodes=320"])  # long enough to be inspected before the roles exit
    seen: dict[str, bool] = {}

    def inspect(sup, board) -> None:
        """All five roles at one tick, or none: a role not started yet, or already exiting (a zombie
        on a loaded machine, CI 2026-12-04), is looked at again at the next tick."""
        if seen or len(board.heartbeats) < 3:
            return
        maps = {}
        for name in ("local-0", "local-2", "central", "env", "learner"):
            pid = sup.pid(name)
            if pid is None:
                return
            try:
                maps[name] = _maps_torch(pid)
            except psutil.NoSuchProcess:  # ZombieProcess included
                return
        seen.update(maps)

    res = launch(cfg, RuntimeSettings(run_id="edge"), tmp_path / "run", chaos=inspect)
    assert res.summary["completed"]
    assert seen == {"local-0": False, "local-2": False, "central": False, "env": False, "learner": True}
