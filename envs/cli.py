"""Commands of this package, added to the `hammer` CLI by `hammer.cli`.

`hammer envs list` shows what `make_vec_env` can build. The env-worker benchmark
(`hammer bench workers`: in-process vs subprocess multiwalker stepping) lives in `benchmarks/`.
"""

from __future__ import annotations

import typer

DEFAULT_N = 3  # the paper's smaller team size; every name also works at N=5


def register(app: typer.Typer) -> None:
    """Add this package's commands to the top-level app."""
    envs = typer.Typer(help="Environments: the registry behind make_vec_env.", no_args_is_help=True)
    app.add_typer(envs, name="envs")

    @envs.command("list")
    def list_envs(n_agents: int = typer.Option(DEFAULT_N, "--n-agents", "-n", help="team size N to describe")) -> None:
        """List env names with N, observation size and action space (builds one copy of each)."""
        from rich.table import Table

        from envs.catalog import env_descriptions
        from envs.registry import make_vec_env
        from hammer.console import table_console

        table = Table("name", "N", "obs dim", "actions", "max steps", "description")
        for name, about in env_descriptions().items():
            v = make_vec_env(name, n_agents, 1)
            s = v.spec
            acts = f"{s.action_dim} discrete" if s.discrete else f"{s.action_dim} in [{s.action_low:g}, {s.action_high:g}]"
            table.add_row(name, str(s.n_agents), str(s.obs_dim), acts, str(s.max_steps), about)
            v.close()
        table_console().print(table)
        typer.echo("Any PettingZoo parallel env is accepted too, as 'module:factory' (e.g. "
                   "'mpe2.simple_spread_v3:parallel_env') with its kwargs.")
