"""The lightweight roles: local agents and the central server of a real `hammer up` run never load torch
(the central acts with a numpy forward), nor does the env host: only the learner holds torch (which
also shows the check can see torch in a process that has it)."""

from __future__ import annotations

import json

from tests.runtime_helpers import pipelined_run


def test_only_the_learner_runs_torch(tmp_path):
    """The session's pipelined cn3 run (runtime_helpers.pipelined_run, also test_runtime_up's)
    looked at every role's memory maps at one tick while it ran."""
    run = pipelined_run(tmp_path / "run")
    assert json.loads((run / "summary.json").read_text())["completed"]
    seen = json.loads((run / "torch_maps.json").read_text())
    assert seen == {"local-0": False, "local-2": False, "central": False, "env": False, "learner": True}
