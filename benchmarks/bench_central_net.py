"""What each central network costs as N grows: `central_net=concat` (the paper's) vs `set`.

For cn with N agents (observation 6N, 5 actions, previous actions in the state, message length 8,
the default layer sizes, central mode rl so the critic is included) it prints, per network:

* parameters (message part, critic, total) and multiply-accumulates of one state's forward (the
  matmuls: message means + values),
* the central server's acting forward: numpy `message_mean` + `values` on K = 32 states
  (`learning.numpy_policy`, the path on every vector step of `hammer up`), median µs per call,
* the learner's cost: torch forward + backward of the central PPO loss terms' network calls
  (`message_mean` + `values`, summed) on a 200-row minibatch (what one minibatch step of cn's
  K = 32 × T = 25, 4 minibatches does), median ms per call.

Both networks are timed alternately in blocks in one process, so load from other processes hits
both alike; the 1-min load average is printed (the machine is shared: compare the ratio).

    .venv/bin/python -m hammer.benchmarks.bench_central_net [--sizes 10,20,50] [--reps 7] [--json FILE]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # one thread, as every role and run uses (before numpy loads BLAS)

import argparse
import json
import statistics
import time
from pathlib import Path


def _macs(net) -> int:
    """Multiply-accumulates of one state's forward (message means + values), from the weight shapes."""
    from hammer.learning.networks import AgentAttention, CentralAgent

    if isinstance(net, CentralAgent):
        enc = sum(p.numel() for n, p in net.encoder.named_parameters() if n.endswith("weight"))
        crit = sum(p.numel() for n, p in net.critic.named_parameters() if n.endswith("weight"))
        return enc + net.head_weight.numel() + crit

    def block(a: AgentAttention) -> int:
        per_agent = sum(p.numel() for n, p in a.named_parameters() if n.endswith("weight"))
        h = a.query.weight.shape[0]
        return net.n_agents * per_agent + 2 * net.n_agents * net.n_agents * h  # + scores and the weighted sum

    return block(net.msg) + block(net.critic)


def _median_time(fn, reps: int, inner: int) -> float:
    out = []
    for _ in range(reps):
        t0 = time.perf_counter()
        for _ in range(inner):
            fn()
        out.append((time.perf_counter() - t0) / inner)
    return statistics.median(out)


def measure(n: int, reps: int) -> list[dict]:
    import numpy as np
    import torch
    from hammer.learning.config import merge_config
    from hammer.learning.networks import make_central
    from hammer.learning.numpy_policy import numpy_central

    torch.set_num_threads(1)
    obs_dim, act_dim, k, rows = 6 * n, 5, 32, 200
    rng = np.random.default_rng(0)
    nets, rows_out = {}, []
    for kind in ("concat", "set"):
        cfg = merge_config("cn5", overrides=[f"n_agents={n}", f"central_net={kind}"])
        torch.manual_seed(0)
        net = make_central(cfg.wiring, obs_dim, act_dim, cfg.central_hidden, cfg.critic_hidden)
        nets[kind] = (net, numpy_central(net.export_numpy()))
    state = rng.normal(size=(k, n * (obs_dim + act_dim))).astype(np.float32)
    batch = torch.from_numpy(rng.normal(size=(rows, n * (obs_dim + act_dim))).astype(np.float32))
    times = {kind: {"numpy": [], "train": []} for kind in nets}
    inner_np, inner_tr = max(2, 2000 // n), max(2, 400 // n)
    for _ in range(reps):  # alternate the two nets, block by block
        for kind, (net, npn) in nets.items():
            times[kind]["numpy"].append(_median_time(lambda npn=npn: (npn.message_mean(state), npn.values(state)),
                                                     1, inner_np))

            def train_step(net=net) -> None:
                loss = net.message_mean(batch).sum() + net.values(batch).sum()
                net.zero_grad(set_to_none=True)
                loss.backward()

            times[kind]["train"].append(_median_time(train_step, 1, inner_tr))
    for kind, (net, _) in nets.items():
        msg = sum(p.numel() for name, p in net.named_parameters() if not name.startswith("critic"))
        crit = sum(p.numel() for name, p in net.named_parameters() if name.startswith("critic"))
        rows_out.append({"n": n, "net": kind, "state_dim": n * (obs_dim + act_dim), "params_msg": msg,
                         "params_critic": crit, "params": msg + crit, "macs_per_state": _macs(net),
                         "acting_numpy_us_k32": statistics.median(times[kind]["numpy"]) * 1e6,
                         "train_fwd_bwd_ms_200rows": statistics.median(times[kind]["train"]) * 1e3})
    return rows_out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="10,20,50")
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    load0 = os.getloadavg()[0]
    rows = [r for n in (int(x) for x in args.sizes.split(",")) for r in measure(n, args.reps)]
    load1 = os.getloadavg()[0]
    print(f"cn, M = 8, rl (critic included), 1 thread; 1-min load {load0:.1f} -> {load1:.1f}")
    print("| N | net | state | params (msg + critic) | MACs / state | acting, numpy, K=32 (µs) | "
          "train fwd+bwd, 200 rows (ms) |")
    print("| ---: | --- | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        print(f"| {r['n']} | {r['net']} | {r['state_dim']:,} | {r['params']:,} ({r['params_msg']:,} + "
              f"{r['params_critic']:,}) | {r['macs_per_state']:,} | {r['acting_numpy_us_k32']:,.0f} | "
              f"{r['train_fwd_bwd_ms_200rows']:.2f} |")
    if args.json:
        args.json.write_text(json.dumps({"load": [load0, load1], "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
