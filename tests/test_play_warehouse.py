"""`hammer play` on a warehouse team: the picture is drawn from rware's own state (not from the
observation), and the CLI writes a GIF of the archived step-3 team with its messages beside each frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from hammer.envs.registry import make_vec_env
from hammer.serve.play import _ROBOT_COLOURS, CELL, warehouse_frame
from typer.testing import CliRunner

from hammer.cli import app

ROOT = Path(__file__).resolve().parents[1]
TEAM = ROOT / "docs/results/runs/rware-cmp/rware-tiny-2ag-hammer-rl-ep2000-s0"


def _pixel(img: np.ndarray, x: float, y: float) -> tuple[int, ...]:
    return tuple(int(v) for v in img[int(y), int(x)])


def test_the_frame_shows_every_robot_shelf_and_goal_where_rware_has_them():
    env = make_vec_env("rware", 3, 1, env_kwargs={"size": "tiny"})
    env.reset(5)
    rng = np.random.default_rng(5)
    checked = {"robot": 0, "loaded": 0, "requested": 0, "shelf": 0, "goal": 0}
    for _ in range(80):
        env.step(rng.integers(0, 5, (1, 3)))
        wh = env.envs[0]
        img = warehouse_frame(wh, env.settings.sensor_range)
        robots = {(a.x, a.y) for a in wh.agents}
        for k, a in enumerate(wh.agents):
            dx, dy = (5, 0) if a.dir.value in (0, 1) else (0, 5)  # beside the heading line
            colour = _ROBOT_COLOURS[k]
            want = tuple(v // 2 for v in colour) if a.carrying_shelf is not None else colour
            assert _pixel(img, (a.x + 0.5) * CELL + dx, (a.y + 0.5) * CELL + dy) == want
            checked["loaded" if a.carrying_shelf is not None else "robot"] += 1
        requested = {s.id for s in wh.request_queue}
        for s in wh.shelfs:
            if (s.x, s.y) in robots:
                continue
            want = (220, 50, 50) if s.id in requested else (90, 130, 200)
            assert _pixel(img, (s.x + 0.5) * CELL, (s.y + 0.5) * CELL) == want
            checked["requested" if s.id in requested else "shelf"] += 1
        for gx, gy in wh.goals:
            if (gx, gy) not in robots and not any((s.x, s.y) == (gx, gy) for s in wh.shelfs):
                assert _pixel(img, (gx + 0.5) * CELL, (gy + 0.5) * CELL) == (60, 60, 60)
                checked["goal"] += 1
    env.close()
    assert min(checked.values()) > 0, checked


def test_hammer_play_writes_the_warehouse_team_with_its_messages(tmp_path):
    from PIL import Image, ImageSequence

    runner = CliRunner()
    r = runner.invoke(app, ["export", str(TEAM), "--out", str(tmp_path / "b")])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["play", str(tmp_path / "b"), "--out", str(tmp_path / "team.gif"), "--episodes", "2",
                            "--max-steps", "12"])
    assert r.exit_code == 0, r.output
    assert "24 frames" in r.output and "2 episodes" in r.output
    # it says how far it is as it goes (a real warehouse episode is a minute of drawing)
    assert "episode 1/2: 12 steps, paper metric" in r.output and "episode 2/2: 12 steps" in r.output
    frames = [np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(Image.open(tmp_path / "team.gif"))]
    assert len(frames) == 24 and frames[0].shape[1] > frames[0].shape[0]  # the floor with the panel beside it
    floor = 10 * CELL  # tiny: 10 columns
    assert not np.array_equal(frames[0][:, floor + 5:], frames[6][:, floor + 5:])  # the messages change
    assert not np.array_equal(frames[0][:, :floor], frames[11][:, :floor])  # the robots move


def test_a_png_is_a_sheet_of_still_frames(tmp_path):
    from PIL import Image

    runner = CliRunner()
    assert runner.invoke(app, ["export", str(TEAM), "--out", str(tmp_path / "b")]).exit_code == 0
    gif, png = tmp_path / "team.gif", tmp_path / "sheet.png"
    for out, extra in ((gif, []), (png, ["--stills", "3"])):
        r = runner.invoke(app, ["play", str(tmp_path / "b"), "--out", str(out), "--episodes", "1", "--max-steps", "9",
                                *extra])
        assert r.exit_code == 0, r.output
    frame = np.asarray(Image.open(gif).convert("RGB"))
    sheet = np.asarray(Image.open(png).convert("RGB"))
    h, w = frame.shape[:2]
    assert sheet.shape == (2 * h, 2 * w, 3)  # three stills, two to a row
    assert np.all(sheet[h:, w:] == 255)  # the fourth place is empty
    assert not np.array_equal(sheet[:h, :w], sheet[:h, w:])  # different steps
