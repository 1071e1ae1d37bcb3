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

from hammer.commands.common import InsecureOpt, ListenOpt, SecureOpt, fail
from hammer.commands.view import ViewOpt, ViewTokenOpt
from hammer.serve.gate_defaults import GATE_DEFAULTS


def register(app: typer.Typer) -> None:
    app.command("export")(export_command)
    app.command("keygen")(keygen_command)
    app.command("sign")(sign_command)
    app.command("serve")(serve_command)
    app.command("push")(push_command)
    app.command("rollback")(rollback_command)
    app.command("play")(play_command)


def export_command(
    run: Annotated[Path, typer.Argument(help="A finished run directory (`hammer train` or `hammer up`): its final/ policy.")],
    out: Annotated[Path, typer.Option(help="The bundle directory to write (manifest.json + safetensors).")],
    force: Annotated[bool, typer.Option(help="Replace an existing bundle at --out.")] = False,
    sign: Annotated[Path | None, typer.Option(help="Sign it with this ed25519 private key (`hammer keygen NAME` "
                                                   "makes NAME.key): agents given --trust NAME.pub load only bundles "
                                                   "it signed.")] = None,
    works_with: Annotated[list[Path] | None, typer.Option(
        "--works-with", help="Repeatable: a folder with a central.safetensors (a bundle, RUN/final, a served run's "
                             "policies/v<N>) this team's local policy also works with; a staged rollout "
                             "(`hammer push --canary`) pairs the canary with the served central network only if "
                             "the bundle declares it.")] = None,
) -> None:
    """Write a self-contained bundle of a trained team: the weights (safetensors) and a manifest (env, spaces,
    variant, message length, fallback, source run and its final metric, sha256 of every file).

    `hammer serve BUNDLE` runs it; `hammer local --bundle BUNDLE` joins a run with it on an edge machine."""
    from hammer.serve.bundle import BundleError, export_bundle

    try:
        b = export_bundle(run, out, force=force, sign=sign, works_with=tuple(works_with or ()))
    except (BundleError, ValueError) as e:
        fail(str(e))
    m = b.manifest
    if sign is not None:
        typer.echo(f"signed with {sign} ({out}/manifest.sig)")
    metric = m["source"]["final_paper_metric_last500"]
    typer.echo(f"bundle {out}: {m['env']['id']} N={m['env_spec']['n_agents']} {m['variant']}"
               f"{'/' + m['central_mode'] if m['central_mode'] else ''}, message length {m['msg_dim']}, "
               f"final metric {'-' if metric is None else f'{metric:.3f}'}, files {', '.join(m['files'])}")


def keygen_command(
    name: Annotated[Path, typer.Argument(help="Writes NAME.key (private, 0600: keep it where bundles are exported) "
                                              "and NAME.pub (give it to the robots).")],
    force: Annotated[bool, typer.Option(help="Replace an existing key pair.")] = False,
) -> None:
    """A new ed25519 key pair for signing bundles (`hammer export --sign NAME.key`, `hammer sign`)."""
    from hammer.serve.signing import new_key

    try:
        private, public = new_key(name, force=force)
    except (FileExistsError, OSError) as e:
        fail(str(e))
    typer.echo(f"private key {private} (keep it secret), public key {public} (agents: --trust {public})")


def sign_command(
    bundle: Annotated[Path, typer.Argument(help="A bundle made by `hammer export`.")],
    key: Annotated[Path, typer.Option(help="The ed25519 private key (`hammer keygen NAME`: NAME.key).")],
) -> None:
    """Sign a bundle: an ed25519 signature of its manifest (which holds every file's sha256 and its own
    seal) in BUNDLE/manifest.sig. The bundle is checked whole first: only an intact bundle is signed."""
    from hammer.serve.bundle import MANIFEST, BundleError, load_bundle
    from hammer.serve.signing import sign_manifest

    try:
        load_bundle(bundle, check_config=False)
        kid = sign_manifest(bundle / MANIFEST, key)
    except (BundleError, ValueError) as e:
        fail(str(e))
    typer.echo(f"signed {bundle} with key {kid} ({bundle}/manifest.sig)")


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
        "--runtime", help="RuntimeSettings field=value, repeatable, e.g. msg_deadline_ms=20, hub_port=7447; with "
                    "--realtime also the fleet's bounds (hold_s, missing_after_s, max_msg_age_s, max_absence_s, msg_wait_s, "
                    "site_hold_s) and "
                    "its links' zenoh_lease_s, reconnect_max_s (docs/fleet.md).")] = None,
    external: Annotated[str | None, typer.Option(
        help="Roles started elsewhere, not launched here (the run waits for them): agent indices (`hammer local "
             "--bundle`) and/or central (`hammer central --run-dir`), e.g. 0,2 or 0,1,2,central.")] = None,
    out: Annotated[Path, typer.Option(help="Root directory for run directories.")] = Path("runs"),
    run_dir: Annotated[Path | None, typer.Option(help="Exact run directory (default: OUT/serve-<bundle>-<time>).")] = None,
    dashboard: Annotated[bool, typer.Option(help="Live terminal dashboard (plain status lines when not a TTY).")] = True,
    secure: SecureOpt = False,
    insecure: InsecureOpt = False,
    listen: ListenOpt = None,
    num_envs: Annotated[int | None, typer.Option(
        min=1, help="Env copies K stepped together (default: the bundle's, as trained); external edge agents are "
                    "told it.")] = None,
    realtime: Annotated[float | None, typer.Option(
        min=0.1, help="Run the team as a fleet at this many Hz (docs/fleet.md): a world that never waits, a central "
                      "agent fed by the robots' uplinks, one torch-free process per robot; K=1.")] = None,
    seconds: Annotated[float | None, typer.Option(
        min=1, help="--realtime: run this long (default: until --episodes episodes).")] = None,
    timeline: Annotated[Path | None, typer.Option(hidden=True, help="--realtime: the world appends per-robot "
                                                                    "totals here once a second (benches).")] = None,
    site: Annotated[Path | None, typer.Option(
        help="--realtime --secure: the identities of this site (`hammer site init`), kept across restarts: robots "
             "keep the files they were given, revoked ones are refused (docs/security.md).")] = None,
    external_site: Annotated[bool, typer.Option(
        help="--realtime, a team with a site feed (rware): the site publishes it from elsewhere "
             "(`hammer.site.SiteFeed`, identity `site`), not the simulated world, which writes the warehouse's "
             "current columns to RUN/warehouse.npy for it (`hammer.site.simulated_warehouse`; docs/fleet.md).")] = False,
    view: ViewOpt = None,
    view_token: ViewTokenOpt = None,
) -> None:
    """Run a trained team as separate processes with frozen weights and no learner: env host, central agent,
    local agents and the policy server, with the dashboard and run directory of `hammer up`.

    SIGTERM (systemd, `docker stop`) or Ctrl-C stops every role, external agents included, and writes
    summary.json (`interrupted`, `stopped_by`); exit 0. Serving again with the same --run-dir keeps the run
    id (edge agents started with --stay join again); the earlier session's results go to RUN/previous/."""
    from rich.console import Console

    from hammer.commands.up import run_up
    from hammer.deploy.plan import plan_serve
    from hammer.serve.bundle import BundleError

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    console = Console(stderr=True)
    if realtime is not None:
        _serve_fleet(console, bundle, realtime, seconds, episodes, seed, fault, chaos, runtime, external, out, run_dir,
                     secure, insecure, listen, num_envs, timeline, site, view, view_token, external_site)
        return
    if external_site:
        fail("--external-site goes with --realtime (a fleet's site feed)")
    if site is not None:
        fail("--site goes with --realtime --secure (a fleet); a lock-stepped served run makes its own identities")
    if seconds is not None:
        fail("--seconds needs --realtime HZ (a lock-stepped served run ends after --episodes)")
    try:
        p = plan_serve(bundle, episodes=episodes, seed=seed, fault=fault, fault_seed=fault_seed, chaos=chaos,
                       runtime=runtime, external=external, out=out, run_dir=run_dir, secure=secure,
                       insecure=insecure, listen=listen, num_envs=num_envs)
    except (BundleError, ValueError) as e:
        fail(str(e))
    b, cfg, settings, path, plan, skip = p.bundle, p.cfg, p.settings, p.run_dir, p.faults, p.external_agents
    console.print(f"serving {bundle} ({b.manifest['variant']}, from run {b.manifest['source']['run']}, "
                  f"env copies K={cfg.num_envs}) -> {path}")
    for lf in plan.links:
        console.print(f"fault: {lf.describe()} (seed {plan.seed})")
    if settings.hub_listen:
        shown = [f"tls/{e.split('/', 1)[1]}" if settings.secure else e for e in settings.hub_listen]
        console.print(f"agents on other machines reach this run at {', '.join(shown)}", soft_wrap=True)
    if skip and settings.secure:  # a bundle carries no identity: the agent needs the run's settings and its own key
        console.print(f"an external agent on another machine needs copies of {path}/runtime.json and of its "
                      f"{path}/identity/{{ca.pem,local-I.pem,local-I.key}} (docs/security.md)", soft_wrap=True)
    from hammer.deploy.launcher import set_aside_served_session

    earlier = set_aside_served_session(path)  # a restarted service: same directory, same run id
    if earlier is not None:
        console.print(f"the previous session's results are in {earlier}")
    run_up(cfg, settings, path, dashboard, console, external_agents=tuple(skip), external_help=p.external_help,
           view=view, view_token=view_token)


def _serve_fleet(console, bundle: Path, hz: float, seconds: float | None, episodes: int, seed: int | None,
                 fault, chaos, runtime, external: str | None, out: Path, run_dir: Path | None, secure: bool,
                 insecure: bool, listen, num_envs: int | None, timeline: Path | None = None,
                 site: Path | None = None, view: str | None = None, view_token: str | None = None,
                 external_site: bool = False) -> None:
    """`hammer serve --realtime HZ`: the fleet launcher (deploy/fleet_launch.py); what does not apply is refused."""
    from hammer.deploy.dashboard import fleet_status_line
    from hammer.deploy.fleet_launch import robot_command, robot_endpoint, run_fleet
    from hammer.deploy.live import LiveRun
    from hammer.deploy.plan import plan_fleet
    from hammer.protocol.access import POLICY
    from hammer.serve.bundle import BundleError

    try:
        plan, path, robots, team = plan_fleet(
            bundle, hz, seconds=seconds, episodes=episodes, seed=seed, fault=fault, chaos=chaos, runtime=runtime,
            external=external, out=out, run_dir=run_dir, secure=secure, insecure=insecure, listen=listen,
            num_envs=num_envs, timeline=timeline, site=site, external_site=external_site)
        roles = ("env", *(("central",) if team.wiring().uses_central else ()), POLICY)
        # the fleet's live files for `hammer view` (RUN/live.json), and the view itself with --view
        watch = LiveRun(path, "fleet", f"{bundle.name} at {hz:g} Hz", robots=int(team.env_spec_data["n_agents"]),
                        roles=roles, view=view, token=view_token)
    except (BundleError, ValueError) as e:
        fail(str(e))
    last = [0.0]

    def tick(board, t: float) -> None:
        watch.tick(board)
        if t - last[0] >= 5.0:
            last[0] = t
            console.print(fleet_status_line(board, t))

    console.print(f"serving {bundle} as a fleet at {hz:g} Hz -> {path} (each role's command: {path}/fleet.json; "
                  f"hot update: hammer push BUNDLE --to {path}, hammer rollback {path})", soft_wrap=True)
    for i in robots:
        copy = f"{site}/robots/local-{i}/" if site is not None else \
            f"{path}/identity/{{ca.pem,local-{i}.pem,local-{i}.key}}"
        console.print(f"waiting for robot {i}: {robot_command(plan, i, path)}"
                      + (f" (on another machine: --identity a directory holding a copy of {copy})" if secure else "")
                      + " (or hammer.edge.EdgeAgent)", soft_wrap=True)
    if plan.site_external:
        console.print(f"waiting for the site feed: hammer.site.SiteFeed({str(bundle)!r}, run_id={path.name!r}, "
                      f"connect={robot_endpoint(plan)!r}"
                      + (f", identity=<a directory holding a copy of {path}/identity/{{ca.pem,site.pem,site.key}}>"
                         if secure else "") + f"); the simulated warehouse's columns: "
                      f"hammer.site.simulated_warehouse({str(path)!r})", soft_wrap=True)
    if watch.url:
        console.print(f"view: {watch.url}", soft_wrap=True)
    ended = "failed"
    try:
        s = run_fleet(plan, path, on_tick=tick)
        ended = "completed" if s["completed"] else f"stopped: {s['stopped_by']}"
    except (BundleError, ValueError) as e:  # SiteError is a ValueError: one line naming the fix
        fail(str(e))
    finally:
        watch.close(ended)
    w = s["world"]
    console.print(f"{'done' if s['completed'] else 'stopped: ' + str(s['stopped_by'])}: {w.get('ticks', 0)} ticks in "
                  f"{w.get('seconds', 0):.0f} s, {w.get('episodes', 0)} episodes, paper metric "
                  f"{'-' if w.get('paper_metric_mean') is None else round(w['paper_metric_mean'], 2)}; per robot control Hz "
                  f"{[r.get('control_hz') for r in s['robots'].values()]}, defaults "
                  f"{[r.get('defaults') for r in s['robots'].values()]}; summary {path}/summary.json", soft_wrap=True)
    if s["degraded"]:
        console.print(f"degraded: {'; '.join(s['degraded_reasons'])}", soft_wrap=True)


def _gate_defaults() -> str:
    return ", ".join(f"{k} ({v:g})" if isinstance(v, float) else f"{k} ({v})" for k, v in GATE_DEFAULTS.items()
                     if k != "window_episodes") + "."


def push_command(
    bundle: Annotated[Path, typer.Argument(help="The bundle to serve next (`hammer export`).")],
    to: Annotated[Path, typer.Option("--to", help="The run directory of a running `hammer serve` (lock-stepped, or "
                                                  "a fleet: --realtime).")],
    trust: Annotated[list[Path] | None, typer.Option(
        help="Push it only if this ed25519 public key (`hammer keygen`) signed it; repeatable.")] = None,
    canary: Annotated[str | None, typer.Option(
        help="Staged rollout: these local agents (e.g. 0 or 0,2) get the new version first; the command stays, "
             "compares their health with the rest's and the team's metric with the window before the push, and "
             "promotes stage by stage or rolls back on its own (docs/deploy.md).")] = None,
    stages: Annotated[str | None, typer.Option(
        help="With --canary: agents per stage, counts or percentages, ending at 100%, e.g. 1,50%,100% "
             "(default: the canary, then everyone).")] = None,
    gate: Annotated[list[str] | None, typer.Option(
        help="With --canary: limits, NAME=VALUE[,...], repeatable; each with its default: " + _gate_defaults()
             + " metric is paper_metric or team_return; metric_z counts standard errors.")] = None,
    window_episodes: Annotated[int | None, typer.Option(
        help="With --canary: episodes per window (the baseline, each stage, the hold after promotion; default "
             f"{GATE_DEFAULTS['window_episodes']}).")] = None,
) -> None:
    """Hot update of a served team: the bundle becomes the next policy version; every agent switches at the
    same step boundary (the first step that names it); in a fleet (--realtime) each robot switches on its own
    once it holds the version (docs/fleet.md). The dashboard shows the version per role.
    With --canary: a staged rollout with health gates; Ctrl-C before the verdict rolls back."""
    from hammer.serve.bundle import BundleError
    from hammer.serve.push import push

    if canary is None:
        extra = [n for n, v in (("--stages", stages), ("--gate", gate), ("--window-episodes", window_episodes)) if v]
        if extra:
            fail(f"{', '.join(extra)}: only with --canary; fix: add --canary AGENTS or drop {extra[0]}")
        try:
            e = push(bundle, to, trust=tuple(trust or ()))
        except (BundleError, ValueError, OSError) as err:
            fail(str(err))
        typer.echo(f"pushed {bundle} to {to} as policy version {e['version']} (hammer rollback {to} returns to the "
                   "previous one)")
        return
    from hammer.protocol.ranges import parse_indices
    from hammer.serve.canary import CanaryError, Rollout, parse_gate

    def say(text: str) -> None:
        typer.echo(f"{time.strftime('%H:%M:%S')} {text}")

    try:
        agents = parse_indices(canary, "--canary", what="agent")
        r = Rollout(bundle, to, agents, stages, parse_gate(gate or [], window_episodes), tuple(trust or ()), say)
    except (CanaryError, BundleError, ValueError, OSError) as err:
        fail(str(err))
    import signal

    from hammer.runtime.process import take_signals

    take_signals((signal.SIGTERM,))  # a supervisor stopping the command, as Ctrl-C: roll back
    try:
        verdict = r.run()
    except KeyboardInterrupt:
        typer.echo(f"interrupted: rolled back, {to} serves the version before the push" if r.version is not None
                   else "interrupted before the push: nothing changed")
        raise typer.Exit(130) from None
    except (CanaryError, BundleError) as err:
        fail(str(err), code=1)
    if verdict != "promoted":
        raise typer.Exit(1)  # a script sees the rollback


def rollback_command(
    run: Annotated[Path, typer.Argument(help="The run directory of a running `hammer serve`.")],
) -> None:
    """Return a served team to the policy in effect before its latest push (served as a new version)."""
    from hammer.serve.bundle import BundleError
    from hammer.serve.push import refuse_stopped, rollback

    try:
        refuse_stopped(run, "rollback")
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

    import PIL  # noqa: F401  (the training install's: missing, the one-line error comes before the start line)

    from hammer.serve.bundle import BundleError, load_bundle
    from hammer.serve.play import PlayError, play

    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # pygame renders off-screen
    try:
        b = load_bundle(bundle)
        typer.echo(f"playing {episodes} episode{'s' if episodes > 1 else ''} of {bundle} (at most {max_steps} steps "
                   "each; every frame is drawn, a warehouse episode takes about a minute) ...", err=True)
        r = play(b, out, episodes, seed, max_steps, fps, stills, progress=lambda line: typer.echo(line, err=True))
    except (BundleError, PlayError) as e:
        fail(str(e))
    typer.echo(f"wrote {out}: {r['frames']} frames ({r['size'][0]}x{r['size'][1]}), {episodes} episodes, "
               f"paper metric per episode {', '.join(f'{x:.2f}' for x in r['paper_metric'])}")
