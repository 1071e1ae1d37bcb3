"""The edge agent: `hammer local --bundle BUNDLE --agent I ...` with nothing but the bundle.

Why its own entry: an edge device pays for every import. `hammer local --bundle` is dispatched here
by the console script (hammer/entry.py) before the CLI framework (typer, rich) and the other
commands' modules load, and the team's RunConfig (pydantic) is never built: the bundle's manifest
holds what the agent needs (spaces, variant wiring, message length, seed, fallback), read with
json, numpy and safetensors. What stays is the runtime itself: the protocol (pydantic message
models, their fast path), the Zenoh session, `LocalAgentClient`.

The run's settings come from the bundle (fallback) and the run id, or from a copy of the served
run's runtime.json (`--settings`), overridden by `--runtime FIELD=VALUE`. A secure run needs the
agent's three identity files (`--identity DIR`: ca.pem, local-<i>.pem, local-<i>.key;
docs/security.md), no run directory.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
from pathlib import Path


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="hammer local", description="An edge local agent joining a run with only "
                                 "a bundle (made by `hammer export`): acts on its observation + central message.")
    ap.add_argument("--agent", type=int, required=True, help="Local agent index i (0-based).")
    ap.add_argument("--bundle", type=Path, required=True, help="A bundle made by `hammer export`.")
    ap.add_argument("--run-id", help="The run id of the run to join (`hammer serve` prints it; or --settings).")
    ap.add_argument("--connect", help="Zenoh endpoint of the run's hub, e.g. tcp/<hub-host>:7447.")
    ap.add_argument("--zenoh-config", type=Path, help="Zenoh JSON5 config (router/client/TLS deployments).")
    ap.add_argument("--seed", type=int, help="The run's seed (the agent's sampling stream); default the bundle's.")
    ap.add_argument("--settings", type=Path, help="A copy of the served run's runtime.json: its deadlines, "
                                                  "fallback, bounds (and run id).")
    ap.add_argument("--runtime", action="append", default=[], metavar="FIELD=VALUE",
                    help="RuntimeSettings field, repeatable, e.g. msg_deadline_ms=20.")
    ap.add_argument("--identity", type=Path, help="A secure run: the directory with ca.pem, local-<i>.pem and "
                                                  "local-<i>.key (copied from the launcher's RUN/identity/).")
    ap.add_argument("--insecure", action="store_true", help="Run plain (no TLS) although the hub is beyond "
                                                            "loopback: only on a network you trust (docs/security.md).")
    ap.add_argument("--run-dir", type=Path, help=argparse.SUPPRESS)  # refused with a bundle, in one line
    return ap


def agent_spec(bundle, agent: int, seed: int | None):
    """(AgentSpec, num_envs) of agent `agent` from the manifest alone (no RunConfig)."""
    from hammer.local_agent.client import AgentSpec

    m, c = bundle.manifest, bundle.config_data
    env, w = m["env_spec"], bundle.wiring()
    if not 0 <= agent < env["n_agents"]:
        raise ValueError(f"--agent {agent}: this team has agents 0..{env['n_agents'] - 1}")
    return AgentSpec(agent=agent, n_agents=env["n_agents"], obs_dim=w.local_obs_dim(env["obs_dim"]),
                     msg_dim=w.msg_dim, discrete=env["discrete"], action_dim=env["action_dim"],
                     seed=c["seed"] if seed is None else seed, onehot=w.joint_obs), int(c["num_envs"])


def edge_settings(bundle, run_id: str | None, settings_file: Path | None, runtime: list[str]):
    """RuntimeSettings of the run to join: the served run's runtime.json if given, else the bundle's
    fallback; then the --runtime items. Raises ValueError with a one-line reason."""
    from hammer.deploy.settings import RuntimeSettings

    if settings_file is not None:
        try:
            rt = json.loads(Path(settings_file).read_text())
        except (OSError, ValueError) as e:
            raise ValueError(f"--settings {settings_file}: {e}; fix: copy the served run's runtime.json") from None
    else:
        fb = bundle.manifest.get("fallback", {})
        rt = {"fallback": fb.get("mode", "zeros"), "fallback_k": fb.get("k", 3)}
    if run_id:
        rt["run_id"] = run_id
    if not rt.get("run_id"):
        raise ValueError("--bundle needs --run-id (or --settings): the id of the run to join (`hammer serve` prints it)")
    for item in runtime:
        import yaml  # only for --runtime values (yaml.safe_load: numbers, booleans, lists as on `hammer serve`)

        key, eq, val = item.partition("=")
        if not eq:
            raise ValueError(f"--runtime {item!r}: expected FIELD=VALUE, e.g. msg_deadline_ms=20")
        rt[key.strip()] = yaml.safe_load(val)
    rt.update(hub_port=0, zenoh_config_file=None, external=[])  # where to connect is this machine's business
    try:
        return RuntimeSettings.model_validate(rt)
    except Exception as e:  # noqa: BLE001 - pydantic's multi-line report, in one line
        raise ValueError(f"runtime settings: {' '.join(str(e).split())[:400]}") from None


def edge_transport(settings, role: str, n_agents: int, connect: str | None, zenoh_config: Path | None,
                   identity: Path | None, insecure: bool = False):
    """The agent's Zenoh transport: --zenoh-config, or a peer connecting to --connect; TLS with the
    agent's identity files for a secure run."""
    from hammer.protocol.session import TransportConfig

    if connect is None and zenoh_config is None:
        raise ValueError("--bundle needs --connect tcp/<hub>:<port> (or --zenoh-config): where the run's hub listens")
    if zenoh_config is not None:
        transport = TransportConfig(zenoh_config_file=zenoh_config)
    else:
        host = connect.split("/", 1)[-1].rsplit(":", 1)[0]  # a hub on this host: stay on loopback
        transport = TransportConfig(listen=["tcp/127.0.0.1:0" if host in ("127.0.0.1", "localhost", "[::1]")
                                            else "tcp/0.0.0.0:0"], connect=[connect])
    if settings.secure and identity is None:
        raise ValueError("a secure run (secure=true): pass --identity DIR with ca.pem, "
                         f"{role}.pem and {role}.key from the launcher's RUN/identity/")
    if identity is None:
        settings.refuse_plain_beyond_loopback(transport, insecure)
        return transport
    from hammer.protocol.identity import identity_of

    missing = identity_of(identity, role).missing()
    if missing:
        raise ValueError(f"--identity {identity}: {', '.join(p.name for p in missing)} missing; fix: copy them "
                         "from the launcher's RUN/identity/")
    return settings.model_copy(update={"secure": True}).secured(transport, role, None, n_agents,
                                                                 identity_directory=identity)


def edge_inputs(bundle_path: Path, agent: int, run_id: str | None, connect: str | None, zenoh_config: Path | None,
                seed: int | None, settings_file: Path | None = None, runtime: list[str] | None = None,
                identity: Path | None = None, insecure: bool = False):
    """(settings, transport, AgentSpec, num_envs) of an edge agent; ValueError (BundleError) with the reason."""
    from hammer.serve.bundle import load_bundle

    b = load_bundle(bundle_path, check_config=False)
    spec, num_envs = agent_spec(b, agent, seed)
    settings = edge_settings(b, run_id, settings_file, runtime or [])
    return settings, edge_transport(settings, f"local-{agent}", spec.n_agents, connect, zenoh_config, identity,
                                    insecure), \
        spec, num_envs


def run_agent(settings, transport, spec, num_envs: int, step_log_dir: Path | None = None,
              run_dir: Path | None = None, start_step: int | None = None,
              start_version: int | None = None) -> None:
    """Serve as the local agent until the run stops it; the counters go to the log (and the run directory).
    `start_step` / `start_version`: the run's known step and policy version (runtime.bounds), so a forged
    first step or weights cannot anchor the agent; an edge agent from a bundle knows neither."""
    from hammer.local_agent.client import LocalAgentClient
    from hammer.protocol.session import HammerSession

    name = f"local-{spec.agent}"
    try:
        with HammerSession(settings.run_id, transport, settings.faults, sender=name) as s:
            client = LocalAgentClient(s, spec, num_envs, settings.fallback, settings.fallback_k,
                                      settings.msg_deadline_ms / 1e3, settings.weights_timeout_s,
                                      step_log_dir=step_log_dir, step_window=settings.step_window,
                                      max_policy_lag=settings.max_policy_lag, start_step=start_step,
                                      start_version=start_version)
            client.stall_warn_s = settings.stall_warn_s
            client.run()
            logging.getLogger("hammer.local").info("counters: %s", client.counts.as_dict())
            if run_dir is not None:
                from hammer.faults.links import write_role_counters

                try:
                    write_role_counters(run_dir, name, os.getpid(), client.final_counters())
                except OSError as e:  # a remote role without the run dir mounted
                    logging.getLogger("hammer.deploy").warning("could not write counters: %s", e)
    except KeyboardInterrupt:
        pass


def setup_process(role: str) -> None:
    """Line-by-line logging to stderr, the launcher watchdog, SIGTERM/SIGINT as a clean exit (the Zenoh
    session closes)."""
    sys.stderr.reconfigure(line_buffering=True)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format=f"%(asctime)s {role} %(levelname)s %(name)s: %(message)s")
    logging.captureWarnings(True)
    from hammer.deploy.supervisor import parent_watchdog

    parent_watchdog()

    def on_term(signum, frame):
        logging.getLogger("hammer.deploy").warning("%s: %s, stopping", role, signal.Signals(signum).name)
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)


def main(argv: list[str] | None = None) -> int:
    """`hammer local --bundle ...` without the CLI framework; returns the exit code (2: a usage error)."""
    a = parser().parse_args(argv)
    try:
        if a.run_dir is not None:
            raise ValueError("--bundle and --run-dir: pass one of them (a bundle needs no run directory)")
        inputs = edge_inputs(a.bundle, a.agent, a.run_id, a.connect, a.zenoh_config, a.seed, a.settings, a.runtime,
                             a.identity, a.insecure)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    setup_process(f"local-{a.agent}")
    run_agent(*inputs)
    return 0
