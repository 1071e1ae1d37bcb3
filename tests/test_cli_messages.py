"""What a person sees around a run: what will run, an ETA, and the result among the preset's references."""

import time

from hammer.learning.baselines import PAPER_PRESETS, baselines, in_context, preset_of
from hammer.learning.config import PRESETS, merge_config
from typer.testing import CliRunner

from hammer.cli import app
from hammer.commands.train import eta


def test_every_preset_has_random_play_and_the_paper_presets_il_references():
    for name in PRESETS:
        cfg = merge_config(name)
        assert preset_of(cfg) == name
        refs = {b.reference for b in baselines() if b.preset == name}
        assert refs == ({"random play", "IL"} if name in PAPER_PRESETS else {"random play"}), name
        line = in_context(cfg, -20.0)
        assert "random play" in line and ("IL" in line) == (name in PAPER_PRESETS) and "-20.00" in line
    assert in_context(merge_config("cn3", overrides=["env_kwargs.local_ratio=0.2"]), -1.0) is None


def test_eta_is_the_time_left_at_this_session_rate():
    start = (time.monotonic() - 10.0, 100)  # 100 episodes in 10 s since the session started at episode 100
    assert eta(start, 200, 1200) in ("00:01:40", "00:01:39", "00:01:41")
    assert eta((time.monotonic(), 5), 5, 10) == "-"
    slow = (time.monotonic() - 100.0, 0)  # one episode per 100 s, 1000 left: ~27.8 h, not a clock's 03:46
    assert eta(slow, 1, 1001) in ("27:46:40", "27:46:39", "27:46:41")


def test_train_says_what_will_run_and_what_to_do_next(tmp_path):
    res = CliRunner().invoke(app, ["train", "--preset", "cn3", "--variant", "random", "--episodes", "40",
                                   "--out", str(tmp_path), "--set", "num_envs=8", "--set", "rollout_steps=25"])
    assert res.exit_code == 0, res.output
    text = " ".join(res.output.split())
    assert "will run: 40 episodes" in text and "eta" in text
    assert "last-40 paper metric" in text and "random play -26.67" in text
    assert "hammer report" in text and "hammer plot" in text and "hammer train --resume" in text
