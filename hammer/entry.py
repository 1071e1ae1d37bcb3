"""The `hammer` console script: the edge agent starts without the CLI framework.

`hammer local --bundle ...` runs on edge devices, where every import costs memory and start-up
time; it goes straight to `hammer.commands.edge` (argparse, no typer/rich, none of the other
commands' modules). Every other command is the typer app of hammer/cli.py.
"""

from __future__ import annotations

import sys


def main() -> None:
    from hammer.commands.edge import is_edge

    argv = sys.argv[1:]
    if is_edge(argv):
        from hammer.commands.edge import main as edge

        sys.exit(edge(argv[1:]))
    from hammer.cli import main as cli

    cli()


if __name__ == "__main__":
    main()
