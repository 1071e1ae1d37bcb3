"""`hammer export` and `hammer serve`: a trained team out of its run directory, and back into the runtime.

export writes a bundle (serve/bundle.py); serve runs it as `hammer up` does (same processes, same
dashboard, same run directory) with the learner replaced by the frozen-policy server
(serve/policy_server.py): env host, central agent, local agents, no learning.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Annotated

import typer

from hammer.commands.common import InsecureOpt, SecureOpt, fail


def register(app: typer.Typer) -> None:
    app.command("export")(export_command)
    app.command("serve")(serve_command)
    app.command("push")(push_command)
    app.command("rollback")(rollback_command)
    app.command("play")(play_command)


def export_command(
    run: Annotated[Path, typer.Argument(help="A finished run directory (`hammer train` or `hammer up`): its final/ policy.")],
    out: Annotated[Path, typer.Option(help="The bundle directory to write (manifest.json + safetensors).")],
    force: Annotated[bool, typer.Option(help="Replace an existing bundle at --out.")] = False,
) -> None:
    """Write a self-contained bundle of a trained team: the weights (safetensors) and a manifest (env, spaces,
    variant, message length, fallback, source run and its final metric, sha256 of every file).

    `hammer serve BUNDLE` runs it; `hammer local --bundle BUNDLE` joins a run with it on an edge machine."""
    from hammer.serve.bundle import BundleError, export_bundle

    try:
        b = export_bundle(run, out, force=force)
    except (BundleError, ValueError) as e:
        fail(str(e))
    m = b.manifest
    metric = m["source"]["final_paper_metric_last500"]
    typer.echo(f"bundle {out}: {m['env']['id']} N={m['env_spec']['n_agents']} {m['variant']}"
               f"{'/' + m['central_mode'] if m['central_mode'] else ''}, message length {m['msg_dim']}, "
               f"final metric {'-' if metric is None else f'{metric:.3f}'}, files {', '.join(m['files'])}")


def serve_command(
    bundle: Annotated[Path, typer.Argument(help="A bundle made by `hammer export`.")],
    episodes: Annotated[int, typer.Option(help="Episodes to run.")] = 100,
    seed: Annotated[int | None, typer.Option(
        help="Seed of env resets and the agents' sampling (default: the team's training seed, which edge agents "
             "started from the bundle use too).")] = None,
    fault: Annotated[list[str] | None, typer.Option(
        "--fault", help="Link fault, repeatable: LINK:FIELD=VALUE,... e.g. 'central->local:drop=0.2'.")] = None,
    fault_seed: Annotated[int, typer.Option(help="Seed of the link faults.")] = 0,
    chaos: Annotated[list[str] | None, typer.Option(
        "--chaos", help="Process chaos, repeatable: ACTION:ROLE@step=N|t=S[,for=S], e.g. 'kill:central@step=200'.")] = None,
    runtime: Annotated[list[str] | None, typer.Option(
        "--runtime", help="RuntimeSettings field=value, repeatable, e.g. msg_deadline_ms=20, hub_port=7447.")] = None,
    external: Annotated[str | None, typer.Option(
        help="Roles started elsewhere, not launched here (the run waits for them): agent indices (`hammer local "
             "--bundle`) and/or central (`hammer central --run-dir`), e.g. 0,2 or 0,1,2,central.")] = None,
    out: Annotated[Path, typer.Option(help="Root directory for run directories.")] = Path("runs"),
    run_dir: Annotated[Path | None, typer.Option(help="Exact run directory (default: OUT/serve-<bundle>-<time>).")] = None,
    dashboard: Annotated[bool, typer.Option(help="Live terminal dashboard (plain status lines when not a TTY).")] = True,
    secure: SecureOpt = False,
    insecure: InsecureOpt = False,
) -> None:
    """Run a trained team as separate processes with frozen weights and no learner: env host, central agent,
    local agents and the policy server, with the dashboard and run directory of `hammer up`."""
    from rich.console import Console

    from hammer.commands.up import run_up
    from hammer.serve.bundle import BundleError, load_bundle
    from hammer.serve.settings import serve_settings

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    console = Console(stderr=True)
    try:
        b = load_bundle(bundle)
        cfg = b.config(episodes=episodes, msg_dropout=0.0, **({} if seed is None else {"seed": seed}))
        b.check_env_here(cfg)
        skip, roles = _external(external, cfg)
        path = run_dir or out / f"serve-{bundle.name}-{time.strftime('%Y%m%d-%H%M%S')}"
        settings, plan = serve_settings(b, path.name, fault, fault_seed, chaos, [*(runtime or []),
                                                                                   *(["secure=true"] if secure else []),
                                                                                   *(["insecure=true"] if insecure else [])])
        if roles:
            settings = settings.model_copy(update={"external": sorted({*settings.external, *roles})})
        if (skip or roles) and settings.hub_port == 0 and not settings.zenoh_config_file:  # they need the port now
            from hammer.protocol.session import free_loopback_port

            settings = settings.model_copy(update={"hub_port": free_loopback_port()})
    except (BundleError, ValueError) as e:
        fail(str(e))
    console.print(f"serving {bundle} ({b.manifest['variant']}, from run {b.manifest['source']['run']}) -> {path}")
    for lf in plan.links:
        console.print(f"fault: {lf.describe()} (seed {plan.seed})")
    where = f"{'tls' if settings.secure else 'tcp'}/<this host>:{settings.hub_port or '<port>'}"
    if skip and settings.secure:  # a bundle carries no identity: the agent needs the run's settings and its own key
        console.print(f"waiting for external agents {', '.join(map(str, skip))}: copy {path}/runtime.json and "
                      f"identity/{{ca.pem,local-I.pem,local-I.key}} (docs/security.md), then hammer local --bundle "
                      f"{bundle} --agent I --settings runtime.json --identity DIR --connect {where}"
                      + (f" --seed {seed}" if seed is not None else ""), soft_wrap=True)
    elif skip:
        console.print(f"waiting for external agents {', '.join(map(str, skip))}: hammer local --bundle {bundle} "
                      f"--agent I --run-id {settings.run_id} --connect {where}"
                      + (f" --seed {seed}" if seed is not None else ""), soft_wrap=True)
    if roles:
        console.print(f"waiting for the external central agent: hammer central --run-dir {path} --connect {where} "
                      "(the run directory's config.json, runtime.json and env_spec.json are all it needs)", soft_wrap=True)
    run_up(cfg, settings, path, dashboard, console, external_agents=tuple(skip))


def _external(text: str | None, cfg) -> tuple[list[int], list[str]]:
    """--external: (agent indices, other roles) started elsewhere; only the central agent may be one of those."""
    if not text:
        return [], []
    items = [x.strip() for x in text.split(",") if x.strip()]
    roles = sorted({x for x in items if not x.lstrip("-").isdigit()})
    if [r for r in roles if r != "central"] or (roles and not cfg.wiring.uses_central):
        raise ValueError(f"--external {text!r}: expected agent indices and optionally central "
                         f"({'this team has no central agent' if roles == ['central'] else 'e.g. 0,2,central'})")
    out = sorted({int(x) for x in items if x not in roles})
    if any(not 0 <= i < cfg.n_agents for i in out):
        raise ValueError(f"--external {text!r}: this team has agents 0..{cfg.n_agents - 1}")
    return out, roles


def push_command(
    bundle: Annotated[Path, typer.Argument(help="The bundle to serve next (`hammer export`).")],
    to: Annotated[Path, typer.Option("--to", help="The run directory of a running `hammer serve`.")],
) -> None:
    """Hot update of a served team: the bundle becomes the next policy version; every agent switches at the
    same step boundary (the first step that names it). The dashboard shows the version per role."""
    from hammer.serve.bundle import BundleError
    from hammer.serve.push import push

    try:
        e = push(bundle, to)
    except (BundleError, ValueError, OSError) as err:
        fail(str(err))
    typer.echo(f"pushed {bundle} to {to} as policy version {e['version']} (hammer rollback {to} returns to the "
               "previous one)")


def rollback_command(
    run: Annotated[Path, typer.Argument(help="The run directory of a running `hammer serve`.")],
) -> None:
    """Return a served team to the policy in effect before its latest push (served as a new version)."""
    from hammer.serve.bundle import BundleError
    from hammer.serve.push import rollback

    try:
        e = rollback(run)
    except (BundleError, ValueError, OSError) as err:
        fail(str(err))
    typer.echo(f"rolled back {run}: version {e['version']} serves the policy of version {e['restores_version']} "
               f"({e['policy_dir']})")


def play_command(
    bundle: Annotated[Path, typer.Argument(help="A bundle made by `hammer export`.")],
    out: Annotated[Path, typer.Option(help="The GIF to write; a *.png is a sheet of still frames (--stills) "
                                      "for a document.")] = Path("team.gif"),
    episodes: Annotated[int, typer.Option(min=1, help="Episodes to render.")] = 3,
    seed: Annotated[int | None, typer.Option(help="Seed of resets and sampling (default: the team's).")] = None,
    max_steps: Annotated[int, typer.Option(min=1, help="At most this many steps per episode (multiwalker runs 500).")] = 200,
    fps: Annotated[float, typer.Option(min=1, help="Frames per second of the GIF.")] = 8.0,
    stills: Annotated[int, typer.Option(min=1, help="With --out *.png: frames on the sheet, spread evenly "
                                        "over the steps played.")] = 4,
) -> None:
    """Watch a trained team: a few episodes drawn by the environment's own renderer (mpe2, multiwalker;
    the warehouse is drawn by hammer, each robot's view outlined), each agent's message beside the frame.
    Needs the training install."""
    import os

    from hammer.serve.bundle import BundleError, load_bundle
    from hammer.serve.play import PlayError, play

    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # pygame renders off-screen
    try:
        r = play(load_bundle(bundle), out, episodes, seed, max_steps, fps, stills)
    except (BundleError, PlayError) as e:
        fail(str(e))
    typer.echo(f"wrote {out}: {r['frames']} frames ({r['size'][0]}x{r['size'][1]}), {episodes} episodes, "
               f"paper metric per episode {', '.join(f'{x:.2f}' for x in r['paper_metric'])}")
