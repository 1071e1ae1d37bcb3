"""Commands of this package, added to the `hammer` CLI by `hammer.cli`.

`hammer envs list` shows what `make_vec_env` can build; `hammer bench workers` runs
benchmarks/bench_workers.py (in-process vs subprocess multiwalker stepping).
"""

from __future__ import annotations

import runpy
from pathlib import Path

import typer

DEFAULT_N = 3  # the paper's smaller team size; every name also works at N=5


def register(app: typer.Typer, bench: typer.Typer) -> None:
    """Add this package's commands to the top-level app and its `bench` group."""
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

    @bench.command("workers")
    def bench_workers(
        num_envs: int = typer.Option(8, help="K copies"),
        workers: int = typer.Option(2, help="worker processes"),
        n_agents: int = typer.Option(3, help="walkers"),
        steps: int = typer.Option(300, help="batched steps per timed phase"),
    ) -> None:
        """Multiwalker env-steps/s in-process vs SubprocVecEnv vs the ceiling of independent processes (no IPC), same run; prints the speed-ups and load."""
        script = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_workers.py"
        if not script.exists():
            raise typer.BadParameter(f"{script} not found: run from a source checkout of hammer")
        mod = runpy.run_path(str(script), run_name="bench_workers")
        mod["main"]([f"--num-envs={num_envs}", f"--workers={workers}", f"--n-agents={n_agents}", f"--steps={steps}"])
