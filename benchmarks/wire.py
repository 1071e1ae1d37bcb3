"""`hammer bench wire`: what one vector step puts on each link, encoded, against the physical minimum.

    hammer bench wire [BUNDLE] [--num-envs 1,32] [--out FILE.json]

For a team's dimensions (a bundle's, else cn3 with own-observation views: D = 10, M = 4, A = 5,
N = 3) and each K, the messages of one vector step are built as the runtime builds them and
encoded as they go on the wire (msgpack with their headers, stamped as a session stamps them): on
an agent's link its observation and its central message down, its action up (in training with the
message it acted on, echoed for the rollout; serving without it); on the central agent's link the
global state down and N messages up. The physical minimum is what the numbers themselves need: an
agent's link D + M float32 and one action byte per copy, the central link N (D + M) float32 and N
action bytes per copy (a previous action as a byte). Also with the opt-in float16 observations and
messages (`codec.encode(half=True)`). Zenoh's and TCP's framing come on top (`benchmarks/netns.py`
counts veth bytes; not here: it needs network namespaces).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from hammer.benchmarks.results import write_json

STEP = 123_456  # a realistic width: 5 bytes as a msgpack uint32


def _dims(bundle: Path | None) -> dict:
    if bundle is None:
        return {"name": "cn3 (own-observation views)", "D": 10, "M": 4, "A": 5, "N": 3, "discrete": True}
    from hammer.serve.bundle import load_bundle

    b = load_bundle(bundle, check_config=False)
    env = b.env_spec_data
    return {"name": str(bundle), "D": int(env["obs_dim"]), "M": int(b.manifest["msg_dim"]),
            "A": int(env["action_dim"]), "N": int(env["n_agents"]), "discrete": bool(env["discrete"])}


def step_sizes(d: dict, k: int) -> dict:
    """Encoded bytes of each message of one vector step at K = k, per link, and the minimum."""
    from hammer.protocol.codec import encode
    from hammer.protocol.schemas import Action, CentralMsg, GlobalState, LocalObs

    rng = np.random.default_rng(0)
    n, dd, m, a = d["N"], d["D"], d["M"], d["A"]
    idx = np.arange(k, dtype=np.int64)

    def size(msg, half: bool = False) -> int:
        return len(encode(msg, stamp={"sender": ""}, half=half))  # keyed links: the sender is the key's

    h = {"step": STEP, "env_idx": idx}
    obs = rng.standard_normal((k, dd)).astype(np.float32)
    msg = np.tanh(rng.standard_normal((k, m))).astype(np.float32)
    act = rng.integers(0, a, k) if d["discrete"] else np.clip(rng.standard_normal((k, a)), -1, 1).astype(np.float32)
    lo = LocalObs(**h, agent=0, obs=obs, active=np.ones(k, bool), policy_version=3)
    cm = CentralMsg(**h, agent=0, msg=msg, policy_version=3)
    ac = Action(**h, agent=0, action=act, policy_version=3, msg=msg)
    prev = np.eye(a, dtype=np.float32)[rng.integers(0, a, (k, n))]
    gs = GlobalState(**h, obs=rng.standard_normal((k, n, dd)).astype(np.float32), prev_actions=prev,
                     active=np.ones((k, n), bool), policy_version=3)
    local_obs, central_msg, action, state = size(lo), size(cm), size(ac), size(gs)
    # a training run's observation asks for the message back (LocalObs.echo) where there are messages
    local_obs_training = size(LocalObs(**h, agent=0, obs=obs, active=np.ones(k, bool), policy_version=3,
                                       echo=bool(m)))
    action_no_echo = size(Action(**h, agent=0, action=act, policy_version=3))
    half = {"local_obs": size(lo, True), "central_msg": size(cm, True), "action": size(ac, True),
            "global_state": size(gs, True)}
    act_min = 1 if d["discrete"] else 4 * a
    agent_link = local_obs_training + central_msg + action
    agent_link_eval = local_obs + central_msg + action_no_echo
    central_link = state + n * central_msg
    agent_min = k * (4 * (dd + m) + act_min)
    central_min = k * n * (4 * (dd + m) + act_min)
    return {"K": k, "local_obs": local_obs, "local_obs_training": local_obs_training, "central_msg": central_msg,
            "action": action,
            "action_without_echoed_msg": action_no_echo, "global_state": state,
            "agent_link": agent_link, "agent_link_min": agent_min, "agent_link_ratio": round(agent_link / agent_min, 2),
            "agent_link_eval": agent_link_eval, "agent_link_eval_ratio": round(agent_link_eval / agent_min, 2),
            "central_link": central_link, "central_link_min": central_min,
            "central_link_ratio": round(central_link / central_min, 2),
            "float16": {**half, "agent_link_eval": half["local_obs"] + half["central_msg"] + action_no_echo,
                        "central_link": half["global_state"] + n * half["central_msg"]}}


def half_effect(bundle: Path, k: int = 32, steps: int = 200, seed: int = 0) -> dict:
    """What the opt-in float16 observations and messages do to a served team's actions: the team acts
    on float32 (its actions step the env, as served: messages the central agent's means); at every
    step each agent's action is also drawn from the float16-rounded observation and message with the
    same random draws. Returns the fraction of actions that differ (discrete: another id; continuous:
    the largest absolute difference) and the largest change of an input value."""
    from hammer.envs.local_view import local_view_from_config
    from hammer.envs.registry import make_vec_env
    from hammer.learning.central_acting import CentralActing, zero_prev_actions
    from hammer.learning.numpy_policy import NumpyLocalPolicy, numpy_central
    from hammer.learning.rollout import next_prev_actions
    from hammer.learning.sampling import categorical_draw
    from hammer.local_agent.client import AgentSpec, LocalAgent
    from hammer.serve.bundle import CENTRAL, LOCAL, load_bundle
    from safetensors.numpy import load_file

    b = load_bundle(bundle, check_config=False)
    cfg, spec = b.config(), b.env_spec()
    env = make_vec_env(cfg.env, cfg.n_agents, k, env_kwargs=cfg.env_kwargs)
    view, acting = local_view_from_config(cfg, spec), CentralActing.from_config(cfg)
    central = numpy_central(load_file(str(b.path / CENTRAL))) if acting.has_network else None
    policy = NumpyLocalPolicy(load_file(str(b.path / LOCAL)))
    agents = [LocalAgent(AgentSpec.from_config(cfg, spec, i), policy, 0) for i in range(cfg.n_agents)]
    rng = np.random.default_rng(seed)
    half = lambda x: x.astype(np.float16).astype(np.float32)
    obs, _ = env.reset(seed)
    prev = zero_prev_actions(spec, k)
    changed, total, worst_in, worst_out = 0, 0, 0.0, 0.0
    for _ in range(steps):
        msgs = central.message_mean(acting.global_state(obs, prev)) if central is not None else None
        seen = view(obs)
        actions = []
        for i, agent in enumerate(agents):
            o, m = seen[:, i], None if msgs is None else msgs[:, i]
            out32 = policy.actor_out(agent.policy_input(o, m))
            out16 = policy.actor_out(agent.policy_input(half(o), None if m is None else half(m)))
            worst_in = max(worst_in, float(np.abs(half(o) - o).max()),
                           0.0 if m is None else float(np.abs(half(m) - m).max()))
            if spec.discrete:
                u = rng.random(k)
                a32 = categorical_draw(out32, u)[0]
                a16 = categorical_draw(out16, u)[0]
                changed += int((a32 != a16).sum())
            else:
                a32 = out32 + policy.std * rng.standard_normal(out32.shape).astype(np.float32)
                worst_out = max(worst_out, float(np.abs(out16 - out32).max()))
                changed += int((np.abs(out16 - out32) > 1e-3).any(axis=1).sum())
            total += k
            actions.append(a32)
        acts = np.stack(actions, axis=1)
        step = env.step(spec.env_action(acts))
        prev = next_prev_actions(spec, acts, step).prev
        obs = step.obs
    env.close()
    return {"steps": steps, "K": k, "actions": total, "changed": changed, "changed_fraction": changed / total,
            "max_input_change": worst_in, **({} if spec.discrete else {"max_mean_change": worst_out})}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="hammer bench wire", description=__doc__.split("\n\n")[0])
    ap.add_argument("bundle", type=Path, nargs="?")
    ap.add_argument("--num-envs", default="1,32", help="Comma-separated K values.")
    ap.add_argument("--out", type=Path)
    a = ap.parse_args(argv)
    d = _dims(a.bundle)
    rows = [step_sizes(d, int(k)) for k in a.num_envs.split(",") if k.strip()]
    print(f"{d['name']}: D={d['D']} M={d['M']} A={d['A']} N={d['N']} ({'discrete' if d['discrete'] else 'continuous'}); "
          "encoded bytes per vector step (headers included, Zenoh/TCP framing not):")
    for r in rows:
        f16 = r["float16"]
        print(f"  K={r['K']:>3}: obs {r['local_obs']} B, central msg {r['central_msg']} B, action {r['action']} B "
              f"(of which the echoed message {r['action'] - r['action_without_echoed_msg']}: training only), "
              f"global state {r['global_state']} B")
        print(f"         agent link {r['agent_link']:,} B training, {r['agent_link_eval']:,} B serving, against a "
              f"minimum of {r['agent_link_min']:,} B: {r['agent_link_ratio']}x / {r['agent_link_eval_ratio']}x; "
              f"central link {r['central_link']:,} B against {r['central_link_min']:,} B: {r['central_link_ratio']}x")
        print(f"         float16 (opt-in): obs {f16['local_obs']} B, msg {f16['central_msg']} B, agent link serving "
              f"{f16['agent_link_eval']:,} B ({f16['agent_link_eval'] / r['agent_link_min']:.2f}x), central link "
              f"{f16['central_link']:,} B ({f16['central_link'] / r['central_link_min']:.2f}x)")
    out = {"dims": d, "rows": rows}
    if a.bundle is not None:
        eff = out["float16_effect"] = half_effect(a.bundle)
        print(f"float16 observations and messages, this team ({eff['steps']} steps, K={eff['K']}): "
              f"{eff['changed']} of {eff['actions']:,} actions differ ({100 * eff['changed_fraction']:.3f}%), "
              f"inputs moved by at most {eff['max_input_change']:.2g}")
    write_json(a.out, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
