"""How often the lite edge agent (plain Python, no numpy) acts otherwise than the numpy agent.

    python -m hammer.benchmarks.lite_agreement BUNDLE [--steps 10000] [--out FILE.json]

The bundle's team plays its env at K=1 in one process: the numpy local agents (`client.LocalAgent`)
act and step the env, the numpy central agent sends the messages (as `hammer play` runs a team);
beside each numpy agent a lite agent (`local_agent.lite.LiteLocalAgent`: the same weights, seed
and stream) acts on the same observation and message. Both draw one uniform per step from the same
stream, so they stay in step whatever they choose; an action differs only where a float32 logit of
the pure-Python forward differs from numpy's BLAS in its last bits and the uniform falls within
that of a class boundary. Reports the fraction of agent-steps whose actions differ, and the largest
logit difference seen. Discrete MLP teams only (what the lite agent runs).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np


def agreement(bundle_path: Path, steps: int = 10_000, seed: int | None = None) -> dict:
    from hammer.envs.local_view import local_view_from_config
    from hammer.envs.registry import make_vec_env
    from hammer.learning.central_acting import CentralActing, zero_prev_actions
    from hammer.learning.numpy_policy import numpy_central
    from hammer.learning.rollout import next_prev_actions
    from hammer.learning.sampling import ActingStreams
    from hammer.local_agent.client import AgentSpec, LocalAgent
    from hammer.local_agent.lite import LiteLocalAgent
    from hammer.serve.bundle import load_bundle
    from safetensors.numpy import load as load_safetensors

    bundle = load_bundle(bundle_path)
    cfg = bundle.config(msg_dropout=0.0, num_envs=1, **({} if seed is None else {"seed": seed}))
    spec, w = bundle.env_spec(), cfg.wiring
    if not spec.discrete:
        raise ValueError("the lite agent runs discrete teams only")
    blob = (bundle.path / "local.safetensors").read_bytes()
    specs = [AgentSpec.from_config(cfg, spec, i) for i in range(cfg.n_agents)]
    numpy_agents, lite_agents = [LocalAgent(s) for s in specs], [LiteLocalAgent(s) for s in specs]
    for a in (*numpy_agents, *lite_agents):
        a.load_weights(blob, 0)
    acting, streams = CentralActing.from_config(cfg), ActingStreams(cfg.seed, cfg.n_agents)
    net = (numpy_central(load_safetensors((bundle.path / "central.safetensors").read_bytes()))
           if w.has_central_network else None)
    view = local_view_from_config(cfg, spec)
    env = make_vec_env(cfg.env, cfg.n_agents, 1, env_kwargs=cfg.env_kwargs or None)
    differ, max_logit_diff, t_numpy, t_lite = 0, 0.0, 0.0, 0.0
    try:
        obs, _ = env.reset(cfg.seed)
        prev = zero_prev_actions(spec, 1)
        for _ in range(steps):
            msgs = acting.messages(acting.global_state(obs, prev), streams, 0.0,
                                   net.message_mean if net is not None else None,
                                   net.values if net is not None and acting.rl else None).sent
            seen = obs.reshape(1, -1) if w.joint_obs else view(obs)
            actions = []
            for i, (na, la) in enumerate(zip(numpy_agents, lite_agents)):
                o = seen if w.joint_obs else seen[:, i]
                m = msgs[:, i] if w.msg_dim else None
                t0 = time.perf_counter()
                a_np = na.act(o, m)
                t1 = time.perf_counter()
                a_lite = la.act(o.tolist(), None if m is None else m.tolist())
                t_numpy, t_lite = t_numpy + t1 - t0, t_lite + time.perf_counter() - t1
                differ += a_np.tolist() != a_lite
                x = na.policy_input(o, m)
                max_logit_diff = max(max_logit_diff, float(np.abs(
                    na.policy.actor_out(x)[0] - np.array(la.policy.logits(x[0].tolist()), np.float32)).max()))
                actions.append(a_np[0])
            step = env.step(np.array(actions)[None])
            prev, obs = next_prev_actions(spec, np.array(actions)[None], step).prev, step.obs
    finally:
        env.close()
    n = steps * cfg.n_agents
    return {"bundle": str(bundle_path), "steps": steps, "agent_steps": n, "differ": differ, "fraction": differ / n,
            "max_logit_diff": max_logit_diff, "act_ms_numpy": 1e3 * t_numpy / n, "act_ms_lite": 1e3 * t_lite / n,
            "seed": cfg.seed, "env": cfg.env, "variant": cfg.variant}


def main() -> None:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bundle", type=Path)
    ap.add_argument("--steps", type=int, default=10_000)
    ap.add_argument("--seed", type=int)
    ap.add_argument("--out", type=Path)
    a = ap.parse_args()
    r = agreement(a.bundle, a.steps, a.seed)
    print(json.dumps(r, indent=2))
    if a.out is not None:
        a.out.write_text(json.dumps(r, indent=2) + "\n")


if __name__ == "__main__":
    main()
