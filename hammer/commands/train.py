"""`hammer train`: the in-process vectorised trainer from the command line."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import Annotated

import typer

from hammer.commands.common import ConfigFieldsHelp, fail
from hammer.deploy.dashboard import eta

# What a branch may not change: the checkpoint's networks, buffers and random streams depend on it.
BRANCH_FIXED = ("env", "env_kwargs", "env_adapters", "n_agents", "num_envs", "variant", "central_mode", "central_net",
                "msg_dim", "use_prev_actions", "obs_conv", "actor_hidden", "critic_hidden", "central_hidden")




def train_command(
    preset: Annotated[str | None, typer.Option(help="cn3 | cn5 | mw3 | mw5 (the paper's settings), rware-tiny-2ag | rware-tiny-4ag")] = None,
    variant: Annotated[str | None, typer.Option(
        help="hammer | il | random | centralized; hammer-rl / hammer-backprop (the sweep's spellings) "
             "also set --central-mode")] = None,
    central_mode: Annotated[str | None, typer.Option(help="rl (paper text) | backprop (authors' code)")] = None,
    seed: Annotated[int | None, typer.Option(help="run seed")] = None,
    episodes: Annotated[int | None, typer.Option(help="episode budget (overrides the preset)")] = None,
    config: Annotated[Path | None, typer.Option(help="YAML file of RunConfig fields")] = None,
    set_: Annotated[list[str] | None, typer.Option("--set", help="field=value override, repeatable")] = None,
    out: Annotated[str | None, typer.Option(help="root directory for run directories")] = None,
    name: Annotated[str | None, typer.Option(help="run directory name under --out")] = None,
    run_dir: Annotated[Path | None, typer.Option(help="exact run directory (overrides --out/--name)")] = None,
    resume: Annotated[Path | None, typer.Option(
        help="continue this run directory from its last checkpoint (only --episodes and --set device=... may "
             "change)")] = None,
    branch: Annotated[Path | None, typer.Option(
        help="continue a copy of this run from its last checkpoint into --run-dir, with --set/--seed/--episodes "
             "changes (e.g. --set ent_coef=0.02): what would have happened from there with another setting. "
             "The original is not touched.")] = None,
    quiet: Annotated[bool, typer.Option(help="no progress bar")] = False,
    seeds: Annotated[str | None, typer.Option(
        help="train these seeds as one batched computation, e.g. 0-7 or 0,3,5: one ordinary run directory "
             "per seed under --out (each resumable alone with --resume); not with --seed, --run-dir, "
             "--resume or --branch")] = None,
) -> None:
    """Train a HAMMER team (or a baseline) in-process; writes a run directory."""
    from hammer.learning.config import ConfigError, merge_config
    from hammer.learning.rundir import RunDir

    if variant in ("hammer-rl", "hammer-backprop"):  # as `hammer sweep --variants` spells them
        mode = variant.split("-")[1]
        if central_mode not in (None, mode):
            fail(f"--variant {variant} with --central-mode {central_mode}: they disagree; fix: drop --central-mode")
        variant, central_mode = "hammer", mode
    if seeds is not None:
        from hammer.commands.seeds import train_seeds_command

        train_seeds_command(seeds, preset, variant, central_mode, episodes, config, set_ or [], out, name,
                            conflicts={"--seed": seed, "--run-dir": run_dir, "--resume": resume, "--branch": branch},
                            quiet=quiet)
        return
    try:
        if branch is not None:
            if resume is not None or run_dir is None or any(v is not None for v in (preset, variant, central_mode,
                                                                                     config)):
                raise ConfigError("--branch: needs --run-dir for the new run and takes only --set, --seed and "
                                  "--episodes; fix: e.g. --branch RUN --run-dir RUN-b --set ent_coef=0.02")
            if (branch / "runtime.json").is_file():
                raise ConfigError(f"--branch '{branch}': a `hammer up` run (it has runtime.json); fix: branch a "
                                  "`hammer train` run, or continue this one with `hammer up --resume`")
            src, src_cfg = RunDir.open(branch)
            cfg = merge_config(None, None, set_ or [], {"seed": seed, "episodes": episodes},
                               base=src_cfg.model_dump(mode="json"))
            changed = [f for f in BRANCH_FIXED if getattr(cfg, f) != getattr(src_cfg, f)]
            if changed:
                raise ConfigError(f"--branch: '{changed[0]}' cannot change on a branch (the checkpoint's networks, "
                                  f"buffers or random streams are built on it); fix: drop that --set, or start a new run")
        elif resume is not None:
            # where a run trains is not what it computes: a GPU run may continue on the CPU and back
            moved = [s for s in set_ or [] if s.split("=", 1)[0].strip() == "device"]
            if any(v is not None for v in (preset, variant, central_mode, seed, config)) or len(moved) != len(set_ or []):
                raise ConfigError("--resume: only --episodes (and --set device=...) may be changed when resuming; "
                                  "fix: drop the other options")
            if (resume / "runtime.json").is_file():  # checked before RunDir.open or any write
                raise ConfigError(f"--resume '{resume}': a `hammer up` run (it has runtime.json); fix: continue it "
                                  f"with `hammer up --resume {resume}`")
            rd, cfg = RunDir.open(resume)
            if rd.latest_checkpoint() is None:
                raise ConfigError(f"--resume '{resume}': no checkpoint yet; fix: start it again with --run-dir")
            if episodes is not None or moved:
                cfg = merge_config(None, None, moved, {"episodes": episodes}, base=cfg.model_dump(mode="json"))
        else:
            extra = {"variant": variant, "central_mode": central_mode, "seed": seed, "episodes": episodes,
                     "out": out}
            if "HAMMER_TORCH_THREADS" in os.environ and not any(s.startswith("torch_threads") for s in set_ or []):
                extra["torch_threads"] = int(os.environ["HAMMER_TORCH_THREADS"])
            cfg = merge_config(preset, config, set_ or [], extra)
        from hammer.envs.registry import EnvConfigError
        from hammer.learning.run_env import check_env_fits, make_env
        from hammer.learning.team import torch_device

        torch_device(cfg)  # a device torch cannot use fails before any env or file exists

        try:  # build the env first so a bad env name/kwarg fails before any file is written
            env = make_env(cfg)
            check_env_fits(cfg, env.spec)
        except EnvConfigError as e:
            raise ConfigError(str(e)) from None
        if resume is not None and (episodes is not None or moved):
            rd.write_config(cfg)  # only now that the env, the config and the checkpoint are known good
        if resume is None:
            path = run_dir if run_dir is not None else Path(cfg.out) / (name or cfg.run_name())
            try:
                rd = RunDir.branch(src, path, cfg) if branch is not None else RunDir.create(path, cfg)
            except ConfigError:
                env.close()
                raise
        _run(cfg, rd, env, resume is not None or branch is not None, quiet)
    except ConfigError as e:
        fail(str(e))


def _run(cfg, rd, env, resume: bool, quiet: bool) -> None:
    from rich.console import Console

    console = Console(stderr=True)
    console.print(f"run dir: {rd.path}  ({cfg.env} N={cfg.n_agents}, {cfg.wiring.label}, seed {cfg.seed})")
    console.print(f"will run: {cfg.episodes:,} episodes in this process ({cfg.num_envs} env copies at a time, "
                  f"{env.spec.max_steps} steps each); Ctrl-C stops, `hammer train --resume {rd.path}` continues "
                  "from the last checkpoint")
    started = [None]
    seen = [0]  # episodes done, for the line an interruption prints
    import signal

    from hammer.runtime.process import take_signals

    # SIGTERM (`kill`, a session ending) stops as Ctrl-C does
    term, restore = take_signals((signal.SIGTERM,))
    try:
        summary = _train(cfg, rd, env, resume, quiet, console, started, seen)
    except KeyboardInterrupt:
        ckpt = rd.latest_checkpoint()
        then = (f"`hammer train --resume {rd.path}` continues from the last checkpoint ({ckpt.name})" if ckpt
                else f"no checkpoint yet, nothing to continue; start it again with --run-dir after removing {rd.path}")
        by = "SIGTERM" if term["by"] else "Ctrl-C"
        console.print(f"interrupted ({by}) after {seen[0]:,} of {cfg.episodes:,} episodes: {then}", soft_wrap=True)
        raise typer.Exit(143 if by == "SIGTERM" else 130) from None
    finally:
        restore()
    metric = summary["final_paper_metric_last500"]
    console.print(f"done: {summary['episodes']} episodes, last-{min(500, summary['episodes'])} paper metric "
                  f"{metric:.3f}, {summary['env_steps_per_s_this_session']:,.0f} env-steps/s -> {rd.path}")
    print_next_steps(console, cfg, metric, rd.path, "hammer train")


def _train(cfg, rd, env, resume: bool, quiet: bool, console, started: list, seen: list) -> dict:
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from hammer.learning.trainer import train

    if quiet or not sys.stderr.isatty():
        last = [0]

        def report(p) -> None:  # a line every ~5% for logs
            seen[0] = p.episodes
            if quiet:
                return
            if started[0] is None:
                started[0] = (time.monotonic(), p.episodes)
            if p.episodes - last[0] >= max(1, p.budget // 20):
                last[0] = p.episodes
                console.print(f"episodes {p.episodes}/{p.budget}  env-steps/s {p.steps_per_s:,.0f}  "
                              f"metric(100) {p.running_metric:.2f}  eta {eta(started[0], p.episodes, p.budget)}")

        return train(cfg, rd, resume=resume, env=env, on_progress=report)
    else:
        with Progress(TextColumn("[bold]train"), BarColumn(), MofNCompleteColumn(), TextColumn("episodes"),
                      TextColumn("{task.fields[sps]} env-steps/s"), TextColumn("metric {task.fields[metric]}"),
                      TimeElapsedColumn(), TextColumn("eta"), TimeRemainingColumn(), console=console) as bar:
            task = bar.add_task("train", total=cfg.episodes, sps="-", metric="-")

            def report(p) -> None:
                seen[0] = p.episodes
                bar.update(task, completed=p.episodes, sps=f"{p.steps_per_s:,.0f}",
                           metric=f"{p.running_metric:.2f}")

            return train(cfg, rd, resume=resume, env=env, on_progress=report)


def print_next_steps(console, cfg, metric: float, path, runner: str) -> None:
    """The result among the preset's references and what to run next (shared by both runners)."""
    from hammer.learning.baselines import in_context

    line = in_context(cfg, metric)
    if line:
        console.print(line, soft_wrap=True)
    console.print(f"next: `hammer report {path}` (final table), `hammer plot {path} --out {path}/curves` "
                  f"(learning curve), `tensorboard --logdir {path}`; `{runner} --resume {path} --episodes N` "
                  "continues it (also after Ctrl-C)", soft_wrap=True)


def register(app: typer.Typer) -> None:
    """Add this package's commands to the top-level app."""
    app.command("train", cls=ConfigFieldsHelp)(train_command)
