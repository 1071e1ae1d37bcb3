"""The `hammer` command line.

Each area of the project owns its own commands in a `cli.py` of its package and adds them here
through a `register(app, bench)` function, so this file stays a table of contents.
"""

from __future__ import annotations

import typer

app = typer.Typer(
    name="hammer",
    help=(
        "Train and run HAMMER teams: one central agent learns to send each lightweight local agent "
        "a short message; local agents act on their own observation plus that message."
    ),
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
bench = typer.Typer(help="Benchmarks that print figures (ratios against a baseline measured in the same run). "
                         "Without a subcommand: the whole-system table (raw env, train, up, latency, RSS).",
                    invoke_without_command=True)
app.add_typer(bench, name="bench")


@bench.callback()
def bench_all(
    ctx: typer.Context,
    episodes: int = typer.Option(320, help="Episodes per runner and preset."),
    json_dir: str = typer.Option("docs/results", "--json-dir", help="Write bench-<date>.json here ('' to skip)."),
) -> None:
    """Whole-system figures in one run; subcommands measure one part each."""
    if ctx.invoked_subcommand is not None:
        return
    from pathlib import Path

    from hammer.bench_suite import run_suite

    run_suite(episodes, Path(json_dir) if json_dir else None)


def _register_all() -> None:
    # Imported lazily per area so `hammer --help` stays fast and the edge client never pulls torch.
    from deploy import cli as deploy_cli
    from deploy.hub import hub_command
    from envs import cli as envs_cli
    from experiments import cli as experiments_cli
    from faults import cli as faults_cli
    from learning import cli as learning_cli
    from protocol import cli as protocol_cli

    app.command("hub")(hub_command)
    for area in (protocol_cli, envs_cli, learning_cli, deploy_cli, experiments_cli, faults_cli):
        area.register(app, bench)


_register_all()


def main() -> None:
    app()


if __name__ == "__main__":
    main()
