"""The role commands of a fleet (`hammer serve --realtime`): the realtime world, the fleet-fed
central agent and the fleet's policy server (hot updates: `hammer push`, `hammer rollback`), one
process each; the robots are `hammer local --bundle ... --fleet` (edge.py).

Hidden from `--help`: the launcher (deploy/fleet_launch.py) starts them, and RUN/fleet.json holds the
exact command of each, for a role that runs on another machine.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from hammer.commands.common import InsecureOpt, fail
from hammer.protocol.transport_log import watch_refused
from hammer.runtime.clock import MSG_WAIT_S, SITE_HOLD_S
from hammer.runtime.process import return_large_blocks, setup_process

BundleOpt = Annotated[Path, typer.Option("--bundle", help="A bundle made by `hammer export`.")]
RunIdOpt = Annotated[str, typer.Option("--run-id", help="The fleet's run id.")]
ConnectOpt = Annotated[str | None, typer.Option("--connect", help="Zenoh endpoint of the fleet's hub.")]
ZenohOpt = Annotated[Path | None, typer.Option("--zenoh-config", help="A Zenoh JSON5 config instead of --connect "
                                                                        "(client of a router, across machines).")]
HzOpt = Annotated[float, typer.Option("--hz", help="Ticks per second.")]
SeedOpt = Annotated[int | None, typer.Option("--seed", help="Seed (default: the team's training seed).")]
IdentityOpt = Annotated[Path | None, typer.Option("--identity", help="A secure fleet: the directory with ca.pem and "
                                                                      "this role's <role>.pem, <role>.key (RUN/identity/).")]
RuntimeOpt = Annotated[list[str] | None, typer.Option("--runtime", help="RuntimeSettings FIELD=VALUE, repeatable: the "
                                                                         "fleet's link settings (zenoh_lease_s, "
                                                                         "reconnect_max_s).")]


def register(app: typer.Typer) -> None:
    app.command("fleet-world", hidden=True)(world_command)
    app.command("fleet-central", hidden=True)(central_command)
    app.command("fleet-policy", hidden=True)(policy_command)


def _open(bundle: Path, run_id: str, connect: str | None, zenoh_config: Path | None, seed: int | None,
          insecure: bool, identity: Path | None, role: str, runtime: list[str] | None = None):
    """The bundle, the team's config at K = 1, and this role's transport: a Zenoh client of the
    fleet's router as the robots are (serve/edge_entry.py), TLS with the role's identity in a secure fleet,
    plain beyond loopback only with --insecure."""
    from hammer.serve.bundle import load_bundle
    from hammer.serve.edge_agent import fleet_check
    from hammer.serve.edge_entry import edge_settings, edge_transport

    b = load_bundle(bundle)
    fleet_check(b)
    cfg = b.config(num_envs=1, **({} if seed is None else {"seed": seed}))
    if connect is None and zenoh_config is None:
        raise ValueError("--connect tcp/<hub>:<port> or --zenoh-config FILE: where the fleet's hub is")
    transport = edge_transport(edge_settings(b, run_id, None, runtime or []), role, cfg.n_agents, connect,
                               zenoh_config, identity, insecure, client=True)
    return b, cfg, transport, run_id


def world_command(bundle: BundleOpt, run_id: RunIdOpt, connect: ConnectOpt = None, zenoh_config: ZenohOpt = None,
                  hz: HzOpt = 20.0,
                  hold_s: Annotated[float, typer.Option(help="Hold a robot's last action this long, then "
                                                             "apply the default.")] = 0.5,
                  msg_wait_s: Annotated[float, typer.Option(help="Wait this long for the central agent's "
                                                                 "messages of a tick before its observations go "
                                                                 "out (they carry them).")] = MSG_WAIT_S,
                  seconds: Annotated[float | None, typer.Option(help="Run this long.")] = None,
                  episodes: Annotated[int | None, typer.Option(help="Run this many episodes.")] = None,
                  run_dir: Annotated[Path | None, typer.Option(help="Where world.json goes.")] = None,
                  timeline: Annotated[Path | None, typer.Option(help="Append a JSON line a second: per-robot "
                                                                     "totals (for benches).")] = None,
                  seed: SeedOpt = None, insecure: InsecureOpt = False, identity: IdentityOpt = None,
                  runtime: RuntimeOpt = None,
                  site_feed: Annotated[bool, typer.Option(help="A team with central-only columns (rware): publish "
                                                                "them as the site (its identity `site`); "
                                                                "--no-site-feed when a site elsewhere does (with "
                                                                "--run-dir, the world writes the warehouse's "
                                                                "current columns to RUN_DIR/warehouse.npy for "
                                                                "it).")] = True) -> None:
    """The realtime world: steps the env at --hz on the robots' latest actions."""
    setup_process("env")
    watch_refused()
    return_large_blocks()
    from contextlib import nullcontext

    from hammer.env_host.world import RealtimeWorld
    from hammer.learning.run_env import make_env
    from hammer.protocol.session import HammerSession
    from hammer.serve.edge_agent import site_columns

    try:
        b, cfg, transport, run_id = _open(bundle, run_id, connect, zenoh_config, seed, insecure, identity, "env",
                                          runtime)
        # in simulation the world is also the site: the feed on its own session, as the site's identity;
        # with the site elsewhere (--no-site-feed), the warehouse's current columns for it in RUN_DIR
        feed, opened = None, nullcontext()
        if cfg.wiring.uses_central and site_columns(b.env_spec_data) is not None:
            from hammer.serve.site_feed import SiteFeed, WarehouseRecord

            if site_feed:  # open before the world's first state (the router is up before the roles)
                feed = SiteFeed(bundle, run_id=run_id, connect=connect, zenoh_config=zenoh_config, identity=identity,
                                insecure=insecure, runtime=tuple(runtime or ()), wait=True, connect_retry_s=60)
                opened = feed
            elif run_dir is not None:
                feed = WarehouseRecord(run_dir)
    except (FileNotFoundError, ValueError, ConnectionError) as e:
        fail(str(e))
    world = None
    try:
        with make_env(cfg) as env, HammerSession(run_id, transport, sender="env") as s, opened:
            world = RealtimeWorld(s, env, hz, hold_s, cfg.seed, episodes=episodes, seconds=seconds, timeline=timeline,
                                  msg_dim=cfg.msg_dim, central=cfg.wiring.uses_central, msg_wait_s=msg_wait_s,
                                  site=feed)
            world.run()
    except KeyboardInterrupt:
        pass
    finally:
        if world is not None and run_dir is not None:
            (Path(run_dir) / "world.json").write_text(json.dumps(world.report(), indent=1))


def central_command(bundle: BundleOpt, run_id: RunIdOpt, connect: ConnectOpt = None, zenoh_config: ZenohOpt = None,
                    hz: HzOpt = 20.0,
                    missing_after_s: Annotated[float, typer.Option(help="A robot silent this long is missing "
                                                                       "(zeros in the state).")] = 0.5,
                    site_hold_s: Annotated[float, typer.Option(help="A site feed silent this long is held no "
                                                                   "longer (its columns zeros in the state).")] = SITE_HOLD_S,
                    seed: SeedOpt = None, insecure: InsecureOpt = False, identity: IdentityOpt = None,
                    runtime: RuntimeOpt = None) -> None:
    """The fleet's central agent: a message per robot for each state of the world (its state from the
    world's, or from a robot's own uplinks); with no world, at --hz."""
    setup_process("central")
    watch_refused()
    return_large_blocks()
    from hammer.central_agent.fleet_central import FleetCentral
    from hammer.protocol.session import HammerSession
    from hammer.serve.bundle import CENTRAL

    try:
        b, cfg, transport, run_id = _open(bundle, run_id, connect, zenoh_config, seed, insecure, identity, "central",
                                                runtime)
        blob = (b.path / CENTRAL).read_bytes() if (b.path / CENTRAL).is_file() else None
    except (FileNotFoundError, ValueError) as e:
        fail(str(e))
    try:
        with HammerSession(run_id, transport, sender="central") as s:
            FleetCentral(s, cfg, b.env_spec(), blob, hz, missing_after_s, site_hold_s=site_hold_s).run()
    except KeyboardInterrupt:
        pass


def policy_command(bundle: BundleOpt, run_id: RunIdOpt,
                   run_dir: Annotated[Path, typer.Option(help="The fleet's run directory: its runtime.json and the "
                                                             "update history (pushes.json) it follows.")],
                   connect: ConnectOpt = None, zenoh_config: ZenohOpt = None, seed: SeedOpt = None,
                   insecure: InsecureOpt = False, identity: IdentityOpt = None, runtime: RuntimeOpt = None) -> None:
    """The fleet's policy server: the bundle as version 0, then each version `hammer push` / `hammer
    rollback` record in RUN/pushes.json (serve/policy_server.py, the class a lock-stepped served run uses)."""
    from hammer.protocol.access import POLICY

    setup_process(POLICY)
    from hammer.protocol.session import HammerSession
    from hammer.runtime.settings import RuntimeSettings
    from hammer.serve.policy_server import PolicyDirError, PolicyServer

    try:
        b, cfg, transport, run_id = _open(bundle, run_id, connect, zenoh_config, seed, insecure, identity, POLICY,
                                                runtime)
        settings = RuntimeSettings.load(run_dir)
    except (FileNotFoundError, ValueError) as e:
        fail(str(e))
    try:
        with HammerSession(run_id, transport, sender=POLICY) as s:
            PolicyServer(s, b.policy_dir, cfg.wiring.has_central_network, settings, run_dir).run()
    except PolicyDirError as e:
        fail(str(e))
    except KeyboardInterrupt:
        pass
