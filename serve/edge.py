"""The edge agent: one local agent of a served team with nothing but the bundle (the library side
of `hammer local --bundle BUNDLE --agent I ...`, whose entry is hammer/commands/edge.py).

Why apart: an edge device pays for every import. The team's RunConfig (pydantic) is never built:
the bundle's manifest holds what the agent needs (spaces, variant wiring, message length, seed,
fallback), read with json, numpy and safetensors. What stays is the runtime itself: the protocol
(pydantic message models, their fast path), the Zenoh session, `LocalAgentClient`.

The run's settings come from the bundle (fallback) and the run id, or from a copy of the served
run's runtime.json (`--settings`), overridden by `--runtime FIELD=VALUE`. A secure run needs the
agent's three identity files (`--identity DIR`: ca.pem, local-<i>.pem, local-<i>.key;
docs/security.md), no run directory.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path


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
    from hammer.runtime.settings import RuntimeSettings

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
        settings.refuse_plain_beyond_loopback(
            transport, insecure, "join a secure run with --settings runtime.json --identity DIR (docs/security.md), or "
                                 "--insecure to accept a plain one on a network you trust")
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
