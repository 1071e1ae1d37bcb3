"""`hammer local --bundle ...`: the edge agent's entry, without the CLI framework.

An edge device pays for every import: the console script (hammer/entry.py) sends `hammer local
--bundle` here before typer, rich and the other commands' modules load. argparse, then the edge
agent of hammer/serve/edge_entry.py.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

# Shared with the typer side of `hammer local` (hammer/commands/common.py), which the edge never imports.
CONNECT_RETRY_HELP = ("Seconds to keep trying to reach the run (its hub or router may start later), logging what "
                      "it waits for; then exit 1 with the reason. 0: forever. Default 300. A --fleet robot without "
                      "--stay also exits 1 after hearing nothing from its fleet this long.")
STAY_HELP = ("Be a service: after the run stops, wait for its next session (a restarted `hammer serve --run-dir` "
             "keeps the run id) and join it; exit cleanly (0, counters logged) on SIGTERM or Ctrl-C. With --fleet: "
             "a robot that outlives server restarts and rejoins on its own.")
NUM_ENVS_HELP = "The served run's env copies K, when `hammer serve --num-envs` changed them (default the bundle's)."


def is_edge(argv: list[str]) -> bool:
    """`local` with `--bundle`: the command line this module parses (the console script and
    `python -m hammer.cli` send it here)."""
    return argv[:1] == ["local"] and any(a == "--bundle" or a.startswith("--bundle=") for a in argv)


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="hammer local", description="An edge local agent joining a run with only "
                                 "a bundle (made by `hammer export`): acts on its observation + central message.")
    ap.add_argument("--agent", type=int, required=True, help="Local agent index i (0-based).")
    ap.add_argument("--bundle", type=Path, required=True, help="A bundle made by `hammer export`.")
    ap.add_argument("--run-id", help="The run id of the run to join (`hammer serve` prints it; or --settings).")
    ap.add_argument("--connect", help="Zenoh endpoint of the run's hub, e.g. tcp/<hub-host>:7447.")
    ap.add_argument("--zenoh-config", type=Path, help="Zenoh JSON5 config (router/client/TLS deployments).")
    ap.add_argument("--seed", type=int, help="The run's seed (the agent's sampling stream); default the bundle's.")
    ap.add_argument("--settings", type=Path, help="A copy of the served run's runtime.json: its deadlines, "
                                                  "fallback, bounds (and run id).")
    ap.add_argument("--runtime", action="append", default=[], metavar="FIELD=VALUE",
                    help="RuntimeSettings field, repeatable, e.g. msg_deadline_ms=20.")
    ap.add_argument("--identity", type=Path, help="A secure run: the directory with ca.pem, local-<i>.pem and "
                                                  "local-<i>.key (copied from the launcher's RUN/identity/).")
    ap.add_argument("--trust", type=Path, action="append", default=[], metavar="KEY.pub",
                    help="Load the bundle only if this ed25519 public key (`hammer keygen`) signed it; repeatable. "
                         "An unsigned or tampered bundle is refused.")
    ap.add_argument("--insecure", action="store_true", help="Run plain (no TLS) although the hub is beyond "
                                                            "loopback: only on a network you trust (docs/security.md).")
    ap.add_argument("--fleet", action="store_true", help="A robot of a realtime fleet (`hammer serve --realtime`): "
                                                         "acts on each observation the world sends it at once, on "
                                                         "the freshest central message (docs/fleet.md).")
    ap.add_argument("--max-msg-age-s", type=float, default=0.5, help="--fleet: the oldest central message acted on "
                                                                     "(else the team's fallback). Default 0.5.")
    ap.add_argument("--connect-retry-s", type=float, default=None, metavar="S", help=CONNECT_RETRY_HELP)
    ap.add_argument("--stay", action="store_true", help=STAY_HELP)
    ap.add_argument("--num-envs", type=int, metavar="K", help=NUM_ENVS_HELP)
    ap.add_argument("--run-dir", type=Path, help=argparse.SUPPRESS)  # refused with a bundle, in one line
    return ap


def options_help() -> str:
    """Every option of `parser()` as `--name VALUE: help`, one paragraph each (the full CLI's
    `hammer local --help` shows them: one definition, two front ends)."""
    out = []
    for a in parser()._actions:
        if not a.option_strings or a.help == argparse.SUPPRESS or "--help" in a.option_strings:
            continue
        value = "" if a.nargs == 0 else f" {a.metavar or a.dest.upper()}"
        out.append(f"{', '.join(a.option_strings)}{value}{' (required)' if a.required else ''}: {a.help}")
    return "\n\n".join(out)


def main(argv: list[str] | None = None) -> int:
    """`hammer local --bundle ...` without the CLI framework; returns the exit code (2: a usage error,
    1: the run was not reached in time)."""
    from hammer.serve.edge_entry import DEFAULT_CONNECT_RETRY_S, JoinError, edge_inputs, run_edge

    a = parser().parse_args(argv)
    if a.fleet:
        return _robot(a)
    try:
        if a.run_dir is not None:
            raise ValueError("--bundle and --run-dir: pass one of them (a bundle needs no run directory)")
        if a.connect_retry_s is not None and a.connect_retry_s < 0:
            raise ValueError(f"--connect-retry-s {a.connect_retry_s:g}: must be >= 0 (0: keep trying forever)")
        inputs = edge_inputs(a.bundle, a.agent, a.run_id, a.connect, a.zenoh_config, a.seed, a.settings, a.runtime,
                             a.identity, a.insecure, a.num_envs, tuple(a.trust))
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    from hammer.runtime.process import setup_process

    setup_process(f"local-{a.agent}")
    try:
        run_edge(*inputs, connect_retry_s=DEFAULT_CONNECT_RETRY_S if a.connect_retry_s is None else a.connect_retry_s,
                 stay=a.stay, weights=a.bundle / "local.safetensors")
    except JoinError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    return 0


def _robot(a: argparse.Namespace) -> int:
    """A robot of a fleet: the SDK's EdgeAgent driven by the world's observations (serve/edge_agent.py)."""
    from hammer.runtime.process import setup_process
    from hammer.serve.edge_agent import EdgeAgent, robot_role
    from hammer.serve.edge_entry import DEFAULT_CONNECT_RETRY_S

    if a.connect_retry_s is not None and a.connect_retry_s < 0:
        print(f"error: --connect-retry-s {a.connect_retry_s:g}: must be >= 0 (0: wait for ever)", file=sys.stderr)
        return 2
    setup_process(f"local-{a.agent}")
    lost_s = DEFAULT_CONNECT_RETRY_S if a.connect_retry_s is None else a.connect_retry_s
    try:
        # a robot is a client of the fleet's router, whose session opens only once the router answers:
        # a router that never does within the bound is a fleet lost like any other
        agent = EdgeAgent(a.bundle, a.agent, run_id=a.run_id, connect=a.connect, zenoh_config=a.zenoh_config,
                          identity=a.identity, insecure=a.insecure, max_msg_age_s=a.max_msg_age_s, seed=a.seed,
                          runtime=tuple(a.runtime), trust=tuple(a.trust), connect_retry_s=lost_s or float("inf"),
                          wait=True, fed_by_world=True)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except ConnectionError:
        print(f"error: local-{a.agent} lost the fleet: nothing from it for {lost_s:g} s (its router at "
              f"{a.connect or a.zenoh_config} never answered); fix: check the address and that the fleet runs",
              file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 0
    try:
        with agent:
            robot = robot_role(agent, stay=a.stay, lost_exit_s=lost_s or None)
            robot.run()
    except KeyboardInterrupt:
        return 0
    if (robot.stop_reason or "").startswith("lost the fleet"):
        print(f"error: local-{a.agent} {robot.stop_reason}", file=sys.stderr)
        return 1
    return 0
