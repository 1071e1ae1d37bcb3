"""compile=true acts through one compiled graph (`learning.fused_acting`); it must act as eager does.

Two teams with the same seed (the same weights), one eager and one compiled, act on the same real
env observations from their own but identically seeded streams, and the eager team's actions step
the env. Every output must agree (float rounding apart: the graph's tanh is 2σ(2x) − 1), the
actions exactly, and the streams must end where the eager ones do (the same draws). A weight
change must reach the compiled graph, which skips its guards after the first call.
"""

import numpy as np
import pytest
import torch
from hammer.learning.central_acting import encode_actions
from hammer.learning.config import merge_config
from hammer.learning.run_env import make_env
from hammer.learning.sampling import ActingStreams
from hammer.learning.team import Team

from tests.runtime_helpers import COMPILE_NETS

FIELDS = ("sent", "mean", "raw", "logp", "value", "keep")


def _act_side_by_side(cfg, steps: int = 12, perturb_at: int | None = None) -> int:
    """Both teams act for `steps` vector steps; returns how many agent-steps the checks covered."""
    env = make_env(cfg)
    eager, fused = Team(cfg, env.spec), Team(cfg.model_copy(update={"compile": True}), env.spec)
    assert eager.fused is None and fused.fused is not None
    s_eager, s_fused = ActingStreams(cfg.seed, cfg.n_agents), ActingStreams(cfg.seed, cfg.n_agents)
    obs, _ = env.reset(3)
    prev = eager.zero_prev_actions(cfg.num_envs)
    covered = 0
    for t in range(steps):
        if t == perturb_at:  # an update changes the weights in place: both teams, the same change
            gen = torch.Generator().manual_seed(t)
            with torch.no_grad():
                for a, b in zip(eager.local.parameters(), fused.local.parameters(), strict=True):
                    delta = 0.3 * torch.randn(a.shape, generator=gen)
                    a.add_(delta)
                    b.add_(delta)
        state = eager.global_state(obs, prev, t + 1)
        c1, *a1 = eager.act(obs, state, s_eager, cfg.msg_dropout)
        c2, *a2 = fused.act(obs, state, s_fused, cfg.msg_dropout)
        for name in FIELDS:
            x, y = getattr(c1, name), getattr(c2, name)
            assert (x.shape, x.dtype) == (y.shape, y.dtype), name
            np.testing.assert_allclose(y, x, atol=2e-6, err_msg=name)
        for name, x, y in zip(("action", "logp", "value"), a1, a2, strict=True):
            assert (x.shape, x.dtype) == (y.shape, y.dtype), name
            np.testing.assert_allclose(y, x, atol=2e-6, err_msg=name)
        np.testing.assert_array_equal(a2[0] if env.spec.discrete else a2[0].round(4),
                                      a1[0] if env.spec.discrete else a1[0].round(4))
        covered += a1[1].size
        st = env.step(eager.env_action(a1[0]))
        obs, prev = st.obs, encode_actions(env.spec, a1[0], st.active)
    assert s_eager.state() == s_fused.state()  # the same draws, in the same amounts
    env.close()
    return covered


@pytest.mark.parametrize("extra", [
    {"variant": "il"},
    {"variant": "hammer", "central_mode": "rl"},
    {"variant": "hammer", "central_mode": "backprop"},
    {"variant": "hammer", "central_mode": "rl", "msg_dropout": 0.3, "missing_prob": 0.2, "missing_window": 3},
    {"variant": "hammer", "central_mode": "rl", "central_net": "set"},
    {"variant": "random"},
    {"variant": "centralized"},
], ids=lambda e: "-".join(f"{v}" for v in e.values()))
def test_fused_acting_acts_as_eager(extra):
    # 4 copies and the small networks: the compiled runs of tests/test_device.py,
    # tests/test_precision.py (hammer) and the teams below (il) act through these graphs, so in one
    # session inductor's cache builds each once.
    cfg = merge_config("cn3", extra=extra, overrides=["num_envs=4", *COMPILE_NETS])
    assert _act_side_by_side(cfg) == 12 * 4 * 3


def test_fused_acting_follows_a_weight_change_and_a_local_view():
    cfg = merge_config("cn3", extra={"variant": "hammer", "central_mode": "rl"},
                       overrides=["num_envs=4", *COMPILE_NETS, "env_kwargs.obs_radius=0.6"])
    _act_side_by_side(cfg, steps=8, perturb_at=4)


def test_fused_acting_with_continuous_actions():
    cfg = merge_config("cn3", extra={"variant": "hammer", "central_mode": "rl", "env": "cn-mpe2",
                                     "env_kwargs": {"continuous_actions": True}}, overrides=["num_envs=4"])
    _act_side_by_side(cfg, steps=6)


def test_fused_acting_with_a_conv_encoder_on_images():
    """Pistonball's frames (grey, 16x16) through the conv stems of the actor and the critic."""
    cfg = merge_config("cn3", overrides=[
        "env=pettingzoo.butterfly.pistonball_v6:parallel_env", "n_agents=3", "env_kwargs.n_pistons=3",
        "env_kwargs.max_cycles=20", "env_adapters=[gray,resize:16x16,flatten]", "obs_conv=[16, 16, 1]",
        "num_envs=2", "variant=hammer", "central_mode=rl"])
    _act_side_by_side(cfg, steps=4)


def test_many_compiled_teams_in_one_process():
    """Dynamo keeps `recompile_limit` graphs per code object (8 by default) and, with fullgraph,
    fails at the next: a script training many compiled runs of different shapes in one process (or
    this test session) must not stop there. With the limit lowered to 2, three team sizes make three
    graphs of the one acting function, the third past the limit: the mechanism of the ninth at the
    default, for three compiles instead of nine (small networks: the limit counts graphs, whatever
    their size)."""
    import torch._dynamo.config as dynamo_config

    # dynamo's own patch, which puts the limit back afterwards (monkeypatch's undo deletes it)
    with dynamo_config.patch(recompile_limit=2):
        for k in range(2, 5):  # 4: the graph of acts_as_eager[il]
            cfg = merge_config("cn3", extra={"variant": "il"},
                               overrides=[f"num_envs={k}", "compile=true", *COMPILE_NETS])
            env = make_env(cfg)
            obs, _ = env.reset(0)
            team = Team(cfg, env.spec)
            _, action, _, _ = team.act(obs, team.global_state(obs, team.zero_prev_actions(k)),
                                       ActingStreams(0, cfg.n_agents))
            assert action.shape == (k, 3)
            env.close()
