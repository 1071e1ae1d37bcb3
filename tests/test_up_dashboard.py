"""The `hammer up` dashboard's rows for rejected messages and stalled roles (hammer/commands/up.py), from
heartbeats as the roles send them: a degraded run must be visible while it runs."""

from __future__ import annotations

import time

from hammer.deploy.dashboard import dashboard_table
from hammer.deploy.launcher import Board
from hammer.learning.config import merge_config
from hammer.protocol.schemas import Heartbeat
from rich.console import Console


def _render(board: Board) -> dict[str, str]:
    """The table as {row label: value}, rendered by rich as a terminal would show it."""
    console = Console(record=True, width=240, color_system=None)
    console.print(dashboard_table(board, merge_config("cn3"), time.monotonic()))
    rows: dict[str, str] = {}
    label = ""
    for line in console.export_text().splitlines():
        cells = [c.strip() for c in line.split("│")[1:-1]]
        if len(cells) != 2:
            continue
        if cells[0]:
            label = cells[0]
            rows[label] = cells[1]
        else:  # a value spread over several lines keeps its label
            rows[label] += "\n" + cells[1]
    return rows


def _hb(role: str, counters: dict | None = None, detail: str = "") -> Heartbeat:
    return Heartbeat(role=role, pid=1, status="running", counters=counters or {}, detail=detail)


def test_a_clean_run_shows_no_rejections_and_no_stalled_row():
    board = Board(heartbeats={"env": _hb("env", {"episodes": 3, "step": 10}), "local-0": _hb("local-0")})
    rows = _render(board)
    assert rows["rejected messages"] == "0"
    assert "stalled" not in rows


def test_rejections_per_role_and_reason_and_stalled_roles_are_shown():
    board = Board(heartbeats={
        "env": _hb("env", {"step": 10, "rejected.step_ahead": 2}),
        "local-0": _hb("local-0", {"rejected.step_ahead": 3, "rejected.control_sender": 1, "rejected.size": 0},
                       detail="stalled: no progress for 41 s (waiting for observations)"),
        "central": _hb("central", {"steps": 9}, detail="stalled: no progress for 35 s (waiting for global states)"),
        "learner": _hb("learner", {"policy_version": 2}, detail="ready")})
    rows = _render(board)
    assert rows["rejected messages"] == "env step_ahead 2; local-0 step_ahead 3, control_sender 1"  # no zero counts
    stalled = rows["stalled"].splitlines()
    assert stalled == ["central: stalled: no progress for 35 s (waiting for global states)",
                       "local-0: stalled: no progress for 41 s (waiting for observations)"]
