"""Commands of this package, added to the `hammer` CLI by `hammer.cli`.

`hammer envs list` shows what `make_vec_env` can build; `hammer envs check ENV` whether an env runs
and with which adapters. The env-worker benchmark
(`hammer bench workers`: in-process vs subprocess multiwalker stepping) lives in `benchmarks/`.
"""

from __future__ import annotations

from typing import Annotated

import typer

from hammer.commands.common import fail

DEFAULT_N = 3  # the paper's smaller team size; every name also works at N=5


def register(app: typer.Typer) -> None:
    """Add this package's commands to the top-level app."""
    envs = typer.Typer(help="Environments: the registry behind make_vec_env.", no_args_is_help=True)
    app.add_typer(envs, name="envs")

    @envs.command("list")
    def list_envs(n_agents: int = typer.Option(DEFAULT_N, "--n-agents", "-n", help="team size N to describe")) -> None:
        """List env names with N, observation size and action space (builds one copy of each)."""
        from rich.table import Table

        from hammer.console import table_console
        from hammer.envs.catalog import env_descriptions
        from hammer.envs.registry import make_vec_env

        table = Table("name", "N", "obs dim", "actions", "max steps", "description")
        for name, about in env_descriptions().items():
            v = make_vec_env(name, n_agents, 1)
            s = v.spec
            acts = f"{s.action_dim} discrete" if s.discrete else f"{s.action_dim} in [{s.action_low:g}, {s.action_high:g}]"
            table.add_row(name, str(s.n_agents), str(s.obs_dim), acts, str(s.max_steps), about)
            v.close()
        table_console().print(table)
        typer.echo("Any PettingZoo parallel env is accepted too, as 'module:factory' (e.g. "
                   "'mpe2.simple_spread_v3:parallel_env') with its kwargs; `hammer envs check module:factory` "
                   "says whether it runs and with which env_adapters.")

    @envs.command("check")
    def check(
        env: Annotated[str, typer.Argument(help="A registered name or module:factory (a module in the current "
                                                "folder is found too), e.g. mpe2.simple_speaker_listener_v4:parallel_env.")],
        set_: Annotated[list[str] | None, typer.Option("--set", help="env_kwargs.K=V, env_adapters=[...] or "
                                                                     "n_agents=N, repeatable, as for `hammer train`.")] = None,
        seconds: Annotated[float, typer.Option(help="How long to step it with random actions for the speed figure.")] = 1.5,
    ) -> None:
        """Build the env, print its agents, spaces, episode length and speed, and say which env_adapters it
        needs or why it cannot run."""
        from rich.markup import escape
        from rich.table import Table

        from hammer.console import table_console
        from hammer.envs.check import check_env
        from hammer.envs.description import EnvConfigError
        from hammer.learning.config import ConfigError, parse_override

        kwargs, adapters, n = {}, None, DEFAULT_N
        try:
            for item in set_ or []:
                keys, value = parse_override(item)
                if keys[0] == "env_kwargs" and len(keys) == 2:
                    kwargs[keys[1]] = value
                elif keys == ["env_adapters"] and isinstance(value, list):
                    adapters = [str(v) for v in value]
                elif keys == ["n_agents"] and isinstance(value, int):
                    n = value
                else:
                    raise ConfigError(f"--set {item!r}: envs check takes env_kwargs.K=V, env_adapters=[a,b] or "
                                      "n_agents=N")
            rep = check_env(env, kwargs, adapters, n, seconds)
        except (ConfigError, EnvConfigError) as e:
            fail(str(e))
        out = table_console()
        if rep.spaces:
            t = Table("agents", "observation space", "action space", title=f"{env}: {len(rep.agents)} agents")
            for row in rep.spaces:
                t.add_row(*(escape(c) for c in row))
            out.print(t)
        if rep.problem:
            out.print(f"cannot run: {rep.problem}", soft_wrap=True, markup=False)
            raise typer.Exit(1)
        out.print(f"episode length: {rep.max_steps or '?'} steps (max_cycles)"
                  + (f", {rep.mean_episode_len:.0f} on average under random actions" if rep.mean_episode_len else ""))
        out.print(f"as a run sees it: obs dim {rep.obs_dim}, actions {rep.actions}, {rep.steps_per_s:,.0f} "
                  "env-steps/s for one copy (random actions)")
        if rep.needed and adapters is None:
            out.print(f"needs adapters: {', '.join(rep.needed)} (envs.adapters)")
        out.print(f"runs: hammer train --set env={env} {rep.fix()}"
                  + "".join(f" --set env_kwargs.{k}={v}" for k, v in kwargs.items()), soft_wrap=True, markup=False)
