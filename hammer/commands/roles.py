"""The role commands (`hammer env-host | central | local | learner`), one process each.

Every role reads the run directory written by `hammer up` (config.json: what is trained;
runtime.json: how the processes talk; env_spec.json: the task's dimensions), opens its own Zenoh
session (never inherited), declares its liveliness token and serves until told to stop.

On another machine, copy those three files into a directory and pass it as --run-dir, plus
--connect tcp/<hub-ip>:<port> (or --zenoh-config for router/TLS setups).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Annotated

import typer

from hammer.commands.common import ConnectOpt, RunDirOpt, ZenohCfgOpt, fail
from hammer.protocol.structs import replace
from hammer.runtime.bounds import known_step, known_version
from hammer.runtime.process import setup_process
from hammer.runtime.settings import read_env_spec


def _settings(run_dir: Path, connect: str | None, zenoh_config: Path | None, role: str):
    """Runtime settings and this role's transport; a secure run adds the role's identity from
    RUN/identity/ (protocol.identity) and the run's access rules."""
    from hammer.runtime.settings import RuntimeSettings

    s = RuntimeSettings.load(run_dir)
    if zenoh_config is not None:
        s = replace(s, zenoh_config_file=str(zenoh_config))
    transport = s.transport_to(connect) if connect is not None and zenoh_config is None else s.transport()
    if s.secure:
        transport = s.secured(transport, role, run_dir, _read_config(run_dir).n_agents)
    # runtime.json's insecure=true (`hammer up --insecure`) is the run's consent
    s.refuse_plain_beyond_loopback(transport, fix="start the run with --secure (docs/security.md), or with "
                                                  "--insecure to accept plain traffic on a network you trust")
    return s, transport


def _served(run_dir: Path) -> bool:
    """Whether the run is served (runtime.json's mode=eval); False where runtime.json cannot be read
    (then `_settings` says why, once the process is set up)."""
    try:
        return json.loads((Path(run_dir) / "runtime.json").read_text()).get("mode") == "eval"
    except (OSError, ValueError, AttributeError):
        return False


def _read_config(run_dir: Path):
    from hammer.learning.config import build_config

    path = Path(run_dir) / "config.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: pass the --run-dir that `hammer up` created")
    return build_config(json.loads(path.read_text()))


def _fault_counters(session) -> dict:
    from hammer.faults.links import flat_fault_counters

    return flat_fault_counters(session.fault_report())


def _write_counters(run_dir: Path, role: str, counters: dict) -> None:
    """Final counters of this process for the launcher's per-link table (faults.links)."""
    import os

    from hammer.faults.links import write_role_counters

    try:
        write_role_counters(run_dir, role, os.getpid(), counters)
    except OSError as e:  # a remote role without the run dir mounted: heartbeats are all the launcher has
        logging.getLogger("hammer.deploy").warning("could not write counters: %s", e)


def _step_log_dir(run_dir: Path) -> Path | None:
    """Where this process logs its link events per step (faults.steplog), if the run dir is writable."""
    from hammer.faults.steplog import STEP_LOG_DIR

    d = Path(run_dir) / STEP_LOG_DIR
    try:
        d.mkdir(exist_ok=True)
    except OSError as e:  # a remote role with a read-only copy of the run files: no per-episode counters
        logging.getLogger("hammer.deploy").warning("no step log: %s", e)
        return None
    return d




def local_epilog() -> str:
    """`hammer local --help`'s second half: the options of `hammer local --bundle` (hammer/commands/edge.py's
    parser, the only definition of them)."""
    from hammer.commands.edge import options_help

    return "With --bundle (an edge agent, or with --fleet a fleet's robot; no run directory):\n\n" + options_help()


def local_command(agent: Annotated[int | None, typer.Option(help="Local agent index i (0-based): one agent, "
                                                                "one process (what an edge device runs).")] = None,
                  agents: Annotated[str | None, typer.Option(
                      help="Serve several local agents from this one process (an agent pool), e.g. 0-19 or "
                           "0,2,5-7; each keeps its own keys, random stream, fallback, fault layer and "
                           "heartbeat.")] = None,
                  run_dir: Annotated[Path | None, typer.Option(
                      help="Run directory made by `hammer up` (config.json, runtime.json, env_spec.json).")] = None,
                  connect: ConnectOpt = None, zenoh_config: ZenohCfgOpt = None,
                  insecure: Annotated[bool, typer.Option(
                      help="Run plain (no TLS) although --connect is beyond loopback: only on a network you trust "
                           "(docs/security.md).")] = False,
                  ) -> None:
    """A local-agent client (--agent i), or a pool of them in one process (--agents 0-19). No torch.

    With --run-dir: a role of a run made by `hammer up`. With --bundle: an edge agent or a fleet's robot,
    started without this CLI framework (hammer/commands/edge.py); its options are listed below."""
    if (agent is None) == (agents is None):
        fail("pass --agent i (one agent) or --agents FIRST-LAST (an agent pool), not both or neither")
    setup_process(f"local-{agent}" if agent is not None else f"locals-{agents}", run_dir)
    if run_dir is None:
        fail("pass --run-dir (a run made by `hammer up`) or --bundle with --run-id and --connect")
    try:
        settings, cfg, spec = _read_settings(run_dir, zenoh_config), _read_config(run_dir), read_env_spec(run_dir)
        members = [agent] if agents is None else _pool_agents(agents, cfg.n_agents)
        transport = _local_transport(settings, run_dir, connect, zenoh_config, members, cfg.n_agents)
        settings.refuse_plain_beyond_loopback(transport, insecure, "join a run started with --secure (docs/security.md), "
                                              "or --insecure to accept a plain one on a network you trust")
    except (FileNotFoundError, ValueError) as e:
        fail(str(e))
    if agents is not None:
        _serve_pool(settings, transport, cfg, spec, members, run_dir)
        return
    if not 0 <= agent < cfg.n_agents:
        fail(f"--agent {agent}: this run has agents 0..{cfg.n_agents - 1}")
    from hammer.local_agent.client import AgentSpec
    from hammer.serve.edge_entry import run_agent

    run_agent(settings, transport, AgentSpec.from_config(cfg, spec, agent), cfg.num_envs,
              step_log_dir=_step_log_dir(run_dir), run_dir=run_dir, start_step=known_step(settings.resume_step),
              start_version=known_version(settings.resume_from))


def _pool_agents(text: str, n_agents: int) -> list[int]:
    from hammer.local_agent.pool import parse_agents

    return parse_agents(text, n_agents)


def _read_settings(run_dir: Path, zenoh_config: Path | None):
    from hammer.runtime.settings import RuntimeSettings

    s = RuntimeSettings.load(run_dir)
    return s if zenoh_config is None else replace(s, zenoh_config_file=str(zenoh_config))


def _local_transport(settings, run_dir: Path, connect: str | None, zenoh_config: Path | None,
                     members: list[int], n_agents: int):
    """The transport of a local-agent process of a run: in a secure run the identity is the agent's
    own (`local-<i>`) or its pool's, which must then be one of the run's pools (identities are made
    by `hammer up`; the CA key is gone afterwards)."""
    transport = settings.transport_to(connect) if connect is not None and zenoh_config is None else settings.transport()
    if not settings.secure:
        return transport
    from hammer.protocol.access import pool_name

    role = f"local-{members[0]}" if len(members) == 1 else pool_name(members)
    pools = dict(settings.pools(n_agents))
    if len(members) > 1 and role not in pools:
        raise ValueError(f"--agents: a secure run admits only its own pools ({', '.join(pools) or 'none'}), each "
                         f"with an identity granted exactly its agents' keys; fix: pass one of those ranges, or "
                         f"--agent i per agent (set runtime agents_per_process when starting the run)")
    return settings.secured(transport, role, run_dir, n_agents)


def _serve_pool(settings, transport, cfg, spec, agents: list[int], run_dir: Path | None) -> None:
    """Several agents, one process and one event loop (`LocalAgentPool`); each agent's counters
    are written as its own, as N single-agent processes would write them."""
    from hammer.local_agent.client import AgentSpec
    from hammer.local_agent.pool import LocalAgentPool
    from hammer.protocol.access import pool_name
    from hammer.protocol.session import HammerSession
    from hammer.runtime.role import process_usage

    specs = [AgentSpec.from_config(cfg, spec, i) for i in agents]
    try:
        # No fault layer on the shared session: each agent gets its own (its own streams and counters).
        with HammerSession(settings.run_id, transport, None, sender=pool_name(agents)) as s:
            pool = LocalAgentPool(s, specs, cfg.num_envs, settings,
                                  step_log_dir=_step_log_dir(run_dir) if run_dir else None,
                                  start_step=known_step(settings.resume_step),
                                  start_version=known_version(settings.resume_from))
            pool.run()
            pool.log.info("%s counters: %s", pool.name, pool.counters())
            if run_dir is not None:
                for m in pool.members:
                    _write_counters(run_dir, m.name, m.final_counters())
                # The process's own figures once, under the pool's name (its agents' counters carry none).
                _write_counters(run_dir, pool.name, {**pool.counters(), **process_usage(pool.cpu_at_start)})
    except KeyboardInterrupt:
        pass


def central_command(run_dir: RunDirOpt, connect: ConnectOpt = None, zenoh_config: ZenohCfgOpt = None) -> None:
    """The central-agent server: one batched forward per vector step, a message per local agent."""
    setup_process("central", run_dir)
    from hammer.central_agent.central_server import CentralServer
    from hammer.protocol.session import HammerSession

    try:
        settings, transport = _settings(run_dir, connect, zenoh_config, "central")
        cfg, spec = _read_config(run_dir), read_env_spec(run_dir)
    except (FileNotFoundError, ValueError) as e:
        fail(str(e))
    try:
        with HammerSession(settings.run_id, transport, settings.faults, sender="central") as s:
            s.wire_float16 = settings.wire_float16
            server = CentralServer(s, cfg, spec, settings, step_log_dir=_step_log_dir(run_dir),
                                   start_step=known_step(settings.resume_step),
                                   start_version=known_version(settings.resume_from))
            server.run()
            logging.getLogger("hammer.central").info("counters: %s", server.counts.as_dict())
            _write_counters(run_dir, "central", server.final_counters())
    except KeyboardInterrupt:
        pass


def env_host_command(run_dir: RunDirOpt, connect: ConnectOpt = None, zenoh_config: ZenohCfgOpt = None) -> None:
    """The env host: steps the K env copies and drives the step loop; writes metrics and the summary."""
    setup_process("env", run_dir)
    from hammer.env_host.host import EnvHost
    from hammer.learning.run_env import make_env
    from hammer.learning.rundir import RunDir
    from hammer.protocol.session import HammerSession
    from hammer.runtime.role import process_usage

    try:
        settings, transport = _settings(run_dir, connect, zenoh_config, "env")
        cfg = _read_config(run_dir)
    except (FileNotFoundError, ValueError) as e:
        fail(str(e))
    env = make_env(cfg)
    rd = RunDir(run_dir)
    host = None
    try:
        with HammerSession(settings.run_id, transport, settings.faults, sender="env") as s:
            s.wire_float16 = settings.wire_float16
            s.declare_alive("env")
            host = EnvHost(s, cfg, env, rd, settings)
            summary = host.run_eval() if settings.mode == "eval" else host.run_training()
            host.log.info("env stopped: %s at step %d, %d episodes", "budget reached" if summary.get("completed")
                          else host.stop_reason or "ended before the budget", host.state.step, host.state.episodes)
            summary["faults"] = s.fault_report()
            host.write_episode_links()
            _write_counters(run_dir, "env", {**host.links.as_dict(), **_fault_counters(s), "step": host.state.step,
                                             "episodes": host.state.episodes, **host.rejection_counters(),
                                             **s.traffic(), **process_usage(host.cpu_at_start)})
            if summary["completed"]:
                rd.write_summary(summary)
            (Path(run_dir) / "env_summary.json").write_text(json.dumps(summary, indent=1))
            host.heartbeat("stopped")
            # The run is over: tell everyone (roles started by hand have no launcher to stop them). In a
            # secure run the access rules keep control to the launcher, which stops everyone as this exits.
            from hammer.protocol.schemas import Control

            s.publish(s.keys.ctl("all"), Control(command="stop"))
    except KeyboardInterrupt:
        logging.getLogger("hammer.env").warning("env stopped: interrupted")
        if host is not None:  # a signal to the whole process group (Ctrl-C): the launcher reports what ran
            summary = {**host.summary(host.state.wall_start), "interrupted": True}
            (Path(run_dir) / "env_summary.json").write_text(json.dumps(summary, indent=1))
    finally:
        rd.close()
        env.close()


def learner_command(run_dir: RunDirOpt,
                    role: Annotated[str, typer.Option(help="team: trains the local policy and the central agent together "
                                                          "(needed for backprop mode; the default).")] = "team",
                    connect: ConnectOpt = None, zenoh_config: ZenohCfgOpt = None) -> None:
    """The learner: receives experience, runs the shared PPO update, broadcasts versioned weights."""
    served = _served(run_dir)  # a served run (mode=eval): the policy server, role `policy`, in the learner's place
    setup_process("policy" if served else f"learner-{role}", run_dir)
    from hammer.protocol.access import LEARNER, POLICY
    from hammer.protocol.session import HammerSession

    if role != "team":
        fail(f"--role {role}: only 'team' is implemented (one learner updates both networks, as backprop mode "
              "requires); see docs/runtime.md")
    try:
        settings, transport = _settings(run_dir, connect, zenoh_config, POLICY if served else LEARNER)
        cfg, spec = _read_config(run_dir), read_env_spec(run_dir)
    except (FileNotFoundError, ValueError) as e:
        fail(str(e))
    if served:  # serve the frozen policy; no torch, no learning
        from hammer.serve.policy_server import PolicyDirError, PolicyServer

        try:
            with HammerSession(settings.run_id, transport, settings.faults, sender=POLICY) as s:
                PolicyServer(s, Path(settings.policy_dir), cfg.wiring.has_central_network, settings, run_dir).run()
        except PolicyDirError as e:
            fail(str(e))
        except KeyboardInterrupt:
            pass
        return
    from hammer.learner.worker import LearnerWorker
    from hammer.learning.rundir import RunDir

    rd = RunDir(run_dir)
    try:
        with HammerSession(settings.run_id, transport, settings.faults, sender=LEARNER) as s:
            worker = LearnerWorker(s, cfg, spec, rd, settings, start_step=known_step(settings.resume_step))
            worker.run()
            _write_counters(run_dir, LEARNER, worker.final_counters())
    except KeyboardInterrupt:
        pass
    finally:
        rd.close()
