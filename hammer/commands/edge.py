"""`hammer local --bundle ...`: the edge agent's entry, without the CLI framework.

An edge device pays for every import: the console script (hammer/entry.py) sends `hammer local
--bundle` here before typer, rich and the other commands' modules load. argparse, then the edge
agent of hammer/serve/edge.py.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


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
    ap.add_argument("--insecure", action="store_true", help="Run plain (no TLS) although the hub is beyond "
                                                            "loopback: only on a network you trust (docs/security.md).")
    ap.add_argument("--run-dir", type=Path, help=argparse.SUPPRESS)  # refused with a bundle, in one line
    return ap


def main(argv: list[str] | None = None) -> int:
    """`hammer local --bundle ...` without the CLI framework; returns the exit code (2: a usage error)."""
    from hammer.serve.edge import edge_inputs, run_agent

    a = parser().parse_args(argv)
    try:
        if a.run_dir is not None:
            raise ValueError("--bundle and --run-dir: pass one of them (a bundle needs no run directory)")
        inputs = edge_inputs(a.bundle, a.agent, a.run_id, a.connect, a.zenoh_config, a.seed, a.settings, a.runtime,
                             a.identity, a.insecure)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    from hammer.runtime.process import setup_process

    setup_process(f"local-{a.agent}")
    run_agent(*inputs)
    return 0
