"""`hammer bench wire`: what one vector step puts on each link, encoded, against the physical minimum.

    hammer bench wire [BUNDLE] [--num-envs 1,32] [--out FILE.json]

For a team's dimensions (a bundle's, else cn3 with own-observation views: D = 10, M = 4, A = 5,
N = 3) and each K, the messages of one vector step are built as the runtime builds them and
encoded as they go on the wire (msgpack with their headers): on an agent's link its observation
and its central message down, its action up (with the message it acted on, echoed for the
learner); on the central agent's link the global state down and N messages up. The physical
minimum is what the numbers themselves need: an agent's link D + M float32 and one action byte
per copy, the central link N (D + M) float32 and N action bytes per copy (a previous action as a
byte). Zenoh's and TCP's framing come on top (`benchmarks/netns.py` counts veth bytes). This is
the baseline the compact wire of issue 31 is measured against.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from hammer.benchmarks.results import write_json

COMMON = {"run": "r" * 24, "ts": 1_764_800_000_000_000_000, "seq": 123_456, "step": 123_456}  # realistic widths


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

    def size(msg, sender: str) -> int:
        return len(encode(msg, stamp={**{x: COMMON[x] for x in ("run", "ts", "seq")}, "sender": sender}))

    h = {"step": COMMON["step"], "env_idx": idx}
    obs = rng.standard_normal((k, dd)).astype(np.float32)
    msg = np.tanh(rng.standard_normal((k, m))).astype(np.float32)
    act = rng.integers(0, a, k) if d["discrete"] else np.clip(rng.standard_normal((k, a)), -1, 1).astype(np.float32)
    local_obs = size(LocalObs(**h, agent=0, obs=obs, active=np.ones(k, bool), policy_version=3), "env")
    central_msg = size(CentralMsg(**h, agent=0, msg=msg, policy_version=3), "central")
    action = size(Action(**h, agent=0, action=act, policy_version=3, msg=msg), "local-0")
    action_no_echo = size(Action(**h, agent=0, action=act, policy_version=3), "local-0")
    prev = np.eye(a, dtype=np.float32)[rng.integers(0, a, (k, n))]
    state = size(GlobalState(**h, obs=rng.standard_normal((k, n, dd)).astype(np.float32), prev_actions=prev,
                             active=np.ones((k, n), bool), policy_version=3), "env")
    act_min = 1 if d["discrete"] else 4 * a
    agent_link = local_obs + central_msg + action
    central_link = state + n * central_msg
    agent_min = k * (4 * (dd + m) + act_min)
    central_min = k * n * (4 * (dd + m) + act_min)
    return {"K": k, "local_obs": local_obs, "central_msg": central_msg, "action": action,
            "action_without_echoed_msg": action_no_echo, "global_state": state,
            "agent_link": agent_link, "agent_link_min": agent_min, "agent_link_ratio": round(agent_link / agent_min, 2),
            "central_link": central_link, "central_link_min": central_min,
            "central_link_ratio": round(central_link / central_min, 2)}


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
        print(f"  K={r['K']:>3}: agent link {r['agent_link']:,} B (obs {r['local_obs']}, msg {r['central_msg']}, "
              f"action {r['action']}, of which the echoed message {r['action'] - r['action_without_echoed_msg']}) "
              f"against a minimum of {r['agent_link_min']:,} B: {r['agent_link_ratio']}x; central link "
              f"{r['central_link']:,} B against {r['central_link_min']:,} B: {r['central_link_ratio']}x")
    write_json(a.out, {"dims": d, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
