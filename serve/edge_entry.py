"""The edge agent: one local agent of a served team with nothing but the bundle (the library side
of `hammer local --bundle BUNDLE --agent I ...`, whose entry is hammer/commands/edge.py).

Why apart: an edge device pays for every import. The team's RunConfig (pydantic) is never built:
the bundle's manifest holds what the agent needs (spaces, variant wiring, message length, seed,
fallback), read with json. What stays is the runtime itself: the protocol (msgspec Structs), the
Zenoh session, and the agent: `local_agent.lite.LiteLocalAgentClient` where it applies (discrete
actions, an MLP policy, K=1: the usual robot), which never imports numpy (numpy and numpy.random
are a large share of an edge agent's memory budget, docs/deploy.md "Footprint"), else `LocalAgentClient` (numpy). `lite_choice` says
which and why, and the agent logs it; HAMMER_EDGE_NUMPY=1 forces the numpy agent.

The run's settings come from the bundle (fallback) and the run id, or from a copy of the served
run's runtime.json (`--settings`), overridden by `--runtime FIELD=VALUE`. A secure run needs the
agent's three identity files (`--identity DIR`: ca.pem, local-<i>.pem, local-<i>.key;
docs/security.md), no run directory.

An edge device is started by its own machine, not by the run (`run_edge`): it may come up before the
hub and keeps trying (`--connect-retry-s`), saying what it waits for; it says it joined only once it
sees the run; and with `--stay` it is a service that outlives each served session (a restarted
`hammer serve --run-dir` keeps its run id) until SIGTERM.
"""

from __future__ import annotations

import json
import logging
import os
import re
import time
from pathlib import Path

from hammer.protocol.structs import replace

DEFAULT_CONNECT_RETRY_S = 300.0  # an agent started long before its server is a configuration mistake
WAIT_LOG_EVERY_S = 10.0
GONE_WAIT_S = 15.0  # after a stop: the longest wait for the stopped session's roles to go (they exit within ~10 s)
STAY_IDLE_S = 120.0  # --stay: a session that sends nothing this long is gone (its server killed without a stop)
_ENDPOINT = re.compile(r"(tcp|udp|tls|quic|ws)/(\[[0-9A-Fa-f:.]+\]|[^\s:/\[\]#?]+):(\d{1,5})([#?]\S*)?")


class JoinError(RuntimeError):
    """The run could not be reached in time; the message is the one-line reason and its fix."""


def agent_spec(bundle, agent: int, seed: int | None):
    """(AgentSpec, num_envs) of agent `agent` from the manifest alone (no RunConfig; its values are
    checked on load, serve.bundle.check_manifest)."""
    from hammer.local_agent.steps import AgentSpec  # numpy-free (the lite agent never loads numpy)

    m, c = bundle.manifest, bundle.config_data
    env, w = m["env_spec"], bundle.wiring()
    if not 0 <= agent < env["n_agents"]:
        raise ValueError(f"--agent {agent}: this team has agents 0..{env['n_agents'] - 1}")
    return AgentSpec(agent=agent, n_agents=env["n_agents"], obs_dim=w.local_obs_dim(env["obs_dim"]),
                     msg_dim=w.msg_dim, discrete=env["discrete"], action_dim=env["action_dim"],
                     seed=c["seed"] if seed is None else seed, onehot=w.joint_obs), int(c["num_envs"])


def lite_choice(spec, num_envs: int, weights: Path | None) -> str | None:
    """None when the edge agent acts without numpy (`local_agent.lite`), else why it takes numpy:
    continuous actions, a conv encoder, more than one env copy (a Python loop per copy), or asked to."""
    if os.environ.get("HAMMER_EDGE_NUMPY", "") not in ("", "0"):
        return "HAMMER_EDGE_NUMPY is set"
    if not spec.discrete:
        return "continuous actions"
    if num_envs != 1:
        return f"K={num_envs} env copies"
    if weights is None:
        return "no local.safetensors to look at"
    from hammer.learning.lite_policy import LiteWeightsError, lite_supported, safetensors_names

    try:
        return lite_supported(safetensors_names(weights))
    except (OSError, LiteWeightsError) as e:
        return str(e)


def edge_settings(bundle, run_id: str | None, settings_file: Path | None, runtime: list[str]):
    """RuntimeSettings of the run to join: the served run's runtime.json if given, else the bundle's
    fallback; then the --runtime items. Raises ValueError with a one-line reason."""
    from hammer.runtime.settings import build_settings

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
    # where to connect is this machine's business
    return build_settings(rt, runtime, fixed={"hub_port": 0, "zenoh_config_file": None, "external": [], "hub_listen": []})


def edge_transport(settings, role: str, n_agents: int, connect: str | None, zenoh_config: Path | None,
                   identity: Path | None, insecure: bool = False, client: bool = False):
    """The agent's Zenoh transport: --zenoh-config, or a peer connecting to --connect; TLS with the
    agent's identity files for a secure run. `client`: a role of a fleet, a Zenoh client of the
    fleet's router (docs/fleet.md), which in a secure fleet relays as the run's `hub` identity."""
    from hammer.protocol.session import TransportConfig

    if connect is None and zenoh_config is None:
        raise ValueError("--bundle needs --connect tcp/<hub>:<port> (or --zenoh-config): where the run's hub listens")
    if zenoh_config is not None:
        transport = settings.link(TransportConfig(zenoh_config_file=zenoh_config))
    else:
        check_endpoint(connect)
        # A hub on this host: stay on loopback. No Zenoh shared memory: its pool is mapped (and counted
        # in the RSS) as soon as a peer on the same host sends a large message, and a robot's peers are
        # on other machines; a --zenoh-config file decides for itself.
        transport = replace(settings.transport_to(connect, client), shared_memory=False)
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
    # the identity makes this agent's link secure, whatever a plain run's settings accepted (insecure)
    return replace(settings, secure=True, insecure=False, secure_hub=settings.secure_hub or client).secured(
        transport, role, None, n_agents, identity_directory=identity)


def check_endpoint(endpoint: str, flag: str = "--connect",
                   fix: str = "give the hub's protocol, address and port, e.g. tcp/192.0.2.1:7447") -> None:
    """A peer session opens whatever it is told to connect to and then waits for it forever, so a
    mistyped --connect would look like a hub not up yet: refuse it in one line instead."""
    m = _ENDPOINT.fullmatch(endpoint)
    if not endpoint.startswith("unixsock-stream/") and (m is None or not 0 < int(m.group(3)) < 65536):
        raise ValueError(f"{flag} {endpoint!r}: not a Zenoh endpoint; fix: {fix}")


def edge_inputs(bundle_path: Path, agent: int, run_id: str | None, connect: str | None, zenoh_config: Path | None,
                seed: int | None, settings_file: Path | None = None, runtime: list[str] | None = None,
                identity: Path | None = None, insecure: bool = False, num_envs: int | None = None,
                trust: tuple[Path, ...] = ()):
    """(settings, transport, AgentSpec, num_envs) of an edge agent; ValueError (BundleError) with the reason.
    `num_envs`: the served run's env copies when `hammer serve --num-envs` changed them (default the bundle's)."""
    from hammer.serve.bundle import load_bundle

    b = load_bundle(bundle_path, check_config=False, trust=trust)
    spec, num_envs_trained = agent_spec(b, agent, seed)
    if num_envs is not None and num_envs < 1:
        raise ValueError(f"--num-envs {num_envs}: must be at least 1 (the served run's env copies)")
    num_envs = num_envs_trained if num_envs is None else num_envs
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
            client = LocalAgentClient(s, spec, num_envs, settings, step_log_dir=step_log_dir, start_step=start_step,
                                      start_version=start_version)
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


def hub_endpoints(transport) -> list[str]:
    """Where this agent looks for the run (for what it logs): --connect, or its Zenoh config's connect endpoints."""
    if transport.connect or transport.zenoh_config_file is None:
        return list(transport.connect)
    cfg = transport.to_zenoh()
    value = json.loads(cfg.get_json("connect/endpoints"))
    if isinstance(value, dict):  # per mode: {"router": [...], "peer": [...], "client": [...]}
        value = value.get(json.loads(cfg.get_json("mode")), [])
    return [str(e) for e in value] if isinstance(value, list) else []


class _Stop:
    """A stop signal (SIGTERM, SIGINT) taken while serving: the signal's name, and the client to end."""

    def __init__(self) -> None:
        self.by: str | None = None
        self.client = None


def _open(settings, transport, name: str, where: str, deadline: float | None, stop: _Stop, log):
    """The agent's session, opened as soon as it can be (protocol.session.open_retrying: a hub or
    router not reachable yet is tried again); None on a stop signal, JoinError past `deadline`."""
    from hammer.protocol.session import HammerSession, OpenTimeout, open_retrying

    try:
        return open_retrying(lambda: HammerSession(settings.run_id, transport, settings.faults, sender=name),
                             deadline, lambda: stop.by is not None,
                             lambda reason: log.info("%s waiting for %s (%s)", name, where, reason),
                             log_every_s=WAIT_LOG_EVERY_S)
    except OpenTimeout as e:
        raise JoinError(f"{name}: {where} not reachable within --connect-retry-s ({e.reason}); fix: check the "
                        "address and that the run's hub or router is up there, or wait longer with "
                        "--connect-retry-s") from None


def _run_seen(session, name: str, watch_liveliness: bool) -> tuple[bool, set[str]]:
    """(linked to anyone, the run's roles seen besides this agent). Where a secure run's access rules
    do not let a local agent ask who is alive (peers meeting directly), a mutual-TLS link with the
    run's CA is the sign: only the run's own roles hold its identities."""
    z = session.zenoh
    linked = any(True for _ in z.info.peers_zid()) or any(True for _ in z.info.routers_zid())
    if not linked:
        return False, set()
    if not watch_liveliness:
        return True, {"a peer of the secure run"}
    return True, session.alive_roles(timeout=0.5) - {name}


def wait_for_run(session, settings, name: str, where: str, deadline: float | None, stop: _Stop, log,
                 ended: float | None = None) -> bool:
    """Until a role of the run is seen (True), or a stop signal (False); JoinError after `deadline`.
    `ended`: when this agent's previous session stopped (--stay): its roles must be gone first, so
    the agent does not join the session that is shutting down (a faster restart is joined once
    GONE_WAIT_S have passed)."""
    watch = session.transport.security is None or settings.secure_hub
    gone, next_log = ended is None, 0.0
    while stop.by is None:
        linked, roles = _run_seen(session, name, watch)
        now = time.monotonic()
        if not gone and (not roles or now - ended > GONE_WAIT_S):
            gone = True
        if gone and roles:
            log.info("%s joined run %s at %s (seen: %s)", name, settings.run_id, where, ", ".join(sorted(roles)))
            return True
        if deadline is not None and now > deadline:
            what = "connected, but no role of the run answered" if linked else "not reachable"
            raise JoinError(f"{name}: run {settings.run_id} at {where}: {what} within --connect-retry-s; fix: check "
                            "the address, the run id and that `hammer serve` runs there (with --listen for other "
                            "machines), or wait longer with --connect-retry-s")
        if now >= next_log:
            if not gone:
                log.info("%s: run %s stopped; waiting for its next session at %s", name, settings.run_id, where)
            elif linked:
                log.info("%s waiting for run %s at %s (connected; no role of the run yet)", name, settings.run_id,
                         where)
            else:
                log.info("%s waiting for %s (not reachable yet)", name, where)
            next_log = now + WAIT_LOG_EVERY_S
        time.sleep(0.1)  # the agent's cold start includes this wait
    return False


def run_edge(settings, transport, spec, num_envs: int, *, connect_retry_s: float = DEFAULT_CONNECT_RETRY_S,
             stay: bool = False, weights: Path | None = None) -> None:
    """Serve as an edge agent started by its own machine: reach the run (retrying for
    `connect_retry_s` s, 0 = forever), act until the run stops it; with `stay`, then wait for the
    run's next session (same run id) and join it, until SIGTERM or SIGINT, which end it cleanly
    (the counters logged, exit 0). Raises JoinError (one line) when the run was never reached.
    `weights`: the bundle's local.safetensors (`lite_choice` reads its tensor names)."""
    import collections
    import signal

    from hammer.runtime.process import take_signals

    log = logging.getLogger("hammer.local")
    name = f"local-{spec.agent}"
    why_numpy = lite_choice(spec, num_envs, weights)
    if why_numpy is None:
        from hammer.local_agent.lite import LiteLocalAgentClient as LocalAgentClient

        log.info("%s acts in plain Python, without numpy (lite agent: discrete MLP policy, K=1)", name)
    else:
        from hammer.local_agent.client import LocalAgentClient

        log.info("%s acts with numpy (%s)", name, why_numpy)
    where = ", ".join(hub_endpoints(transport)) or "the run"
    stop = _Stop()

    def on_signal(signal_name: str) -> None:
        stop.by = signal_name
        log.warning("%s: %s, stopping", name, stop.by)
        if stop.client is not None and stop.client.stop_reason is None:
            stop.client.stop_reason = stop.by  # the role's loop ends at its next turn, as on a stop command

    _, restore = take_signals((signal.SIGTERM, signal.SIGINT), on_signal)
    deadline = time.monotonic() + connect_retry_s if connect_retry_s > 0 else None
    runs, totals, ended = 0, collections.Counter(), None
    try:
        while stop.by is None:
            session = _open(settings, transport, name, where, deadline, stop, log)
            if session is None:
                break
            with session:
                if not wait_for_run(session, settings, name, where, deadline, stop, log, ended):
                    break
                deadline = None  # the run was reached: from now on the agent waits for it as long as it takes
                client = LocalAgentClient(session, spec, num_envs, settings, idle_exit_s=STAY_IDLE_S if stay else None)
                stop.client = client
                if stop.by is not None:
                    client.stop_reason = stop.by
                client.run()
                stop.client = None
                runs += 1
                counts = client.counts.as_dict()
                totals.update(counts)
                log.info("counters: %s", counts)
            ended = time.monotonic()
            if not stay or stop.by is not None:
                break
            log.info("%s: run %s session %d ended (%s); staying for the next one", name, settings.run_id, runs,
                     client.stop_reason)
    finally:
        restore()
    if stop.by is not None:
        log.info("%s stopped by %s after %d session(s) of run %s; counters: %s", name, stop.by, runs,
                 settings.run_id, dict(totals))
