"""The `hammer` command line.

Every command lives in `hammer/commands/`, the top floor (docs/architecture.md, "Floors"): one
module per area adds its commands here through a `register(app)` function, so this file stays a
table of contents, and no library module imports a command. The `hammer bench` group is
`hammer/commands/bench.py`: the measuring code lives in `benchmarks/`, outside the library.
"""

from __future__ import annotations

import typer

app = typer.Typer(
    name="hammer",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)


def _version(value: bool) -> None:
    if value:
        from importlib.metadata import PackageNotFoundError, version

        from hammer import __version__

        try:
            typer.echo(f"hammer {version('hammer-marl')}")
        except PackageNotFoundError:  # run from a checkout without installing
            typer.echo(f"hammer {__version__}")
        raise typer.Exit()


@app.callback()
def _main(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                       help="Print the version and exit.")) -> None:
    """Train and run HAMMER teams: a central agent learns to message lightweight local agents.

    Start with `hammer train --preset cn3` (one process) or `hammer up` (one process per role, over Zenoh).

    `hammer envs check module:factory` says whether a PettingZoo parallel env can run, and how.
    """


def _register_all() -> None:
    # Imported lazily per area so `hammer --help` stays fast and the edge client never pulls torch.
    from hammer.commands import (
        bench,
        envs,
        experiments,
        faults,
        fleet,
        protocol,
        serve,
        site,
        train,
        up,
        view,
    )
    from hammer.commands.hub import hub_command

    app.command("hub")(hub_command)
    for area in (bench, protocol, envs, train, up, experiments, faults, serve, fleet, site, view):
        area.register(app)


_register_all()


# Installed by the `train` extra only: a base (edge) install has none of them.
TRAIN_ONLY = {"torch", "pettingzoo", "mpe2", "matplotlib", "tensorboard", "psutil", "scipy", "gymnasium", "pymunk",
              "PIL"}


def main() -> None:
    """Run the CLI; a command that needs the training install, used on an edge install, fails in one line."""
    import sys

    from hammer.commands.edge import is_edge
    from hammer.commands.edge import main as edge

    if is_edge(sys.argv[1:]):  # `python -m hammer.cli local --bundle ...`: the edge entry, as the console script
        sys.exit(edge(sys.argv[2:]))
    try:
        app()
    except ModuleNotFoundError as e:
        root = (e.name or "").split(".")[0]
        if root not in TRAIN_ONLY:
            raise
        typer.secho(f"error: this command needs the training install ({root} is not installed); "
                    "fix: pip install 'hammer-marl[train]'", fg=typer.colors.RED, err=True)
        sys.exit(2)


if __name__ == "__main__":
    main()
