"""`compile=true` computes the same PPO losses and gradients as eager (to float rounding)."""

import numpy as np
import torch

from envs.registry import make_vec_env
from learning.config import merge_config
from learning.learner import TeamLearner


def test_compiled_losses_match_eager():
    torch.manual_seed(0)
    cfg = merge_config("cn3", overrides=["num_envs=4", "rollout_steps=8", "variant=hammer", "central_mode=rl"])
    env = make_vec_env(cfg.env, cfg.n_agents, cfg.num_envs)
    eager = TeamLearner(cfg, env.spec)
    compiled = TeamLearner(cfg.model_copy(update={"compile": True}), env.spec)
    compiled.team.local.load_state_dict(eager.team.local.state_dict())
    compiled.team.central.load_state_dict(eager.team.central.state_dict())
    rng = np.random.default_rng(0)
    rows, n = 32, cfg.n_agents
    r = {"obs": torch.from_numpy(rng.normal(size=(rows, n, env.spec.obs_dim)).astype(np.float32)),
         "state": torch.from_numpy(rng.normal(size=(rows, eager.team.state_dim)).astype(np.float32)),
         "msg": torch.from_numpy(rng.normal(size=(rows, n, eager.team.msg_dim)).astype(np.float32)),
         "raw": torch.from_numpy(rng.normal(size=(rows, n, eager.team.msg_dim)).astype(np.float32)),
         "act": torch.from_numpy(rng.integers(0, env.spec.action_dim, (rows, n))),
         "logp": torch.full((rows, n), -1.6), "c_logp": torch.full((rows, n), -3.0),
         "adv": torch.from_numpy(rng.normal(size=(rows, n)).astype(np.float32)),
         "ret": torch.from_numpy(rng.normal(size=(rows, n)).astype(np.float32)),
         "c_adv": torch.from_numpy(rng.normal(size=(rows, n)).astype(np.float32)),
         "c_ret": torch.from_numpy(rng.normal(size=(rows, n)).astype(np.float32)),
         "mask": torch.ones(rows, n), "keep": torch.ones(rows, n), "c_mask": torch.ones(rows, n)}
    out = []
    for learner in (eager, compiled):
        learner._full = learner._c_full = True
        local, central, stats = learner._losses(r, True)
        (local + central).backward()
        grads = [p.grad.clone() for p in [*learner.team.local.parameters(), *learner.team.central.parameters()]]
        out.append((local.detach(), central.detach(), torch.stack(stats).detach(), grads))
    (l0, c0, s0, g0), (l1, c1, s1, g1) = out
    torch.testing.assert_close(l1, l0, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(c1, c0, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(s1, s0, rtol=1e-4, atol=1e-5)
    for a, b in zip(g1, g0, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-5)
    assert float(l0) != 0.0
    env.close()
