"""Runtime settings of a distributed run: what the roles need besides the learning config.

The learning config (`learning.config.RunConfig`) decides *what* is trained; these settings
decide how the processes talk: where the hub listens, per-hop deadlines, fallbacks, faults.
Both are written into the run directory by `hammer up` (config.json, runtime.json) and every
role reads them from there, so all roles of a run agree by construction.

Imports stay light (protocol only; the settings are msgspec Structs, `protocol.structs`, no pydantic):
the edge agent reads this too.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import asdict
from pathlib import Path
from typing import Annotated, Literal

import msgspec
from hammer.protocol.fault_injection import FaultSpec
from hammer.protocol.session import (
    FLEET_LEASE_MS,
    FLEET_LOOPBACK_OPEN_TIMEOUT_MS,
    FLEET_OPEN_TIMEOUT_MS,
    FLEET_RECONNECT_MAX_MS,
    TransportConfig,
    is_loopback_endpoint,
    loopback_endpoint,
)
from hammer.protocol.structs import (
    Meta,
    Settings,
    SettingsError,
    default_of,
    dump,
    field_names,
    parse,
    replace,
)

Fallback = Literal["zeros", "last", "last_k"]
Mode = Literal["train", "eval"]


_BOUNDS = ("step_window", "stall_warn_s", "degraded_fraction", "degraded_rejections", "max_absence_s",
           "step_log_max_mb", "trace_max_mb", "log_max_mb", "weights_republish_s",
           "weights_republish_max_s", "zenoh_lease_s", "zenoh_open_timeout_s", "reconnect_max_s", "weights_float16",
           "wire_float16",
           "weights_chunk_bytes", "weights_name_timeout_s")


def auto_agents_per_process(n_agents: int, cores: int | None = None) -> int:
    """How many local agents `hammer up` puts in one process by default: as many as keep the local
    agents' processes to at most 2 x cores - 1 (the env host, the central agent and the learner
    need the rest), so a 2-core machine runs cn3 as today (one process per agent) and cn20 as 3
    pools of 7. More processes than that only wait for a core (docs/scale.md)."""
    if cores is None:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, math.ceil(n_agents / max(1, 2 * cores - 1)))


PLAIN_FIX = ("add --secure (mutual TLS and per-role access rules, docs/security.md), or --insecure to accept that "
             "on a network you trust")


def refuse_plain_beyond_loopback(transport: TransportConfig, secure: bool, insecure: bool,
                                 fix: str = PLAIN_FIX) -> None:
    """A plain run trusts every process that reaches its Zenoh port (docs/security.md): fine on
    loopback, not on a network. Raise ValueError naming what reaches out and the fixes (`fix`: this
    command's way to go secure, or to accept the plain profile)."""
    if secure or insecure or transport.security is not None:
        return
    out = transport.beyond_loopback()
    if out:
        raise ValueError(f"refusing to run plain on {', '.join(out)} (beyond loopback): whoever reaches it could act "
                         f"for any agent, publish weights or stop the run; fix: {fix}")


class RuntimeSettings(Settings):
    """How the roles of one run talk. Defaults suit one host on loopback."""

    # run id: every key is under hammer/<run_id>/
    run_id: str
    # the launcher's Zenoh listen port on 127.0.0.1
    hub_port: Annotated[int, Meta(ge=0, le=65535)] = 0
    # Zenoh JSON5 config for multi-machine runs (router/client/TLS); overrides hub_port
    zenoh_config_file: str | None = None
    # more endpoints the launcher's hub listens on besides 127.0.0.1:hub_port (`hammer serve --listen`), e.g.
    # tcp/192.0.2.1:7447, for agents on other machines; the run's own roles keep loopback; beyond loopback it needs
    # secure=true or insecure=true
    hub_listen: list[str] = msgspec.field(default_factory=list)
    # how long a local agent waits for its central message before a fallback
    msg_deadline_ms: Annotated[float, Meta(gt=0)] = 50.0
    # how long the env host waits for actions before using default actions
    act_deadline_ms: Annotated[float, Meta(gt=0)] = 500.0
    # how long an actor waits for a new policy version
    weights_timeout_s: Annotated[float, Meta(gt=0)] = 60.0
    # 0: synchronous on-policy (actors wait for every update; reproduces `hammer train`). 1+: the env host collects
    # the next rollout with the previous version while the learner updates; the learner corrects with that version's
    # log-probs and reports the lag
    max_policy_lag: Annotated[int, Meta(ge=0, le=4)] = 0
    # message used when it is late: zeros, last, or last_k
    fallback: Fallback = "zeros"
    # last_k: reuse the last message for at most k steps, then zeros
    fallback_k: Annotated[int, Meta(ge=0)] = 3
    # seeded fault injection on publishes (off when None)
    faults: FaultSpec | None = None
    # wait this long for every role to be alive
    startup_timeout_s: Annotated[float, Meta(gt=0)] = 60.0
    # train: learn to the budget; eval: run a frozen policy (policy_dir)
    mode: Mode = "train"
    # eval: directory with local.safetensors (+ central.safetensors), e.g. RUN/final
    policy_dir: str | None = None
    # env host writes trace.npz (obs, messages, actions, masks per step)
    trace: bool = False
    # process chaos events, e.g. 'kill:central@step=200'
    chaos: list[str] = msgspec.field(default_factory=list)
    # the link-level fault plan (for display)
    fault_links: list[dict] = msgspec.field(default_factory=list)
    # continue from this update: the learner loads checkpoints/ckpt_<U>, the env host host_state/ckpt_<U>.json (set by
    # `hammer up --resume`, never by hand)
    resume_from: Annotated[int, Meta(ge=0)] | None = None
    # mutual TLS with per-run identities (RUN/identity/) and per-role access rules (protocol.access); see
    # docs/security.md
    secure: bool = False
    # accept the plain profile beyond loopback (`--insecure`): without it a run whose endpoints reach past this
    # machine refuses to start unless secure=true
    insecure: bool = False
    # secure run whose roles meet through a `hammer hub --run-dir RUN` router (several machines): a `hub` identity is
    # created and every role accepts what the router relays
    secure_hub: bool = False
    # roles `hammer up` does not start (started by hand, e.g. local-2): it waits for their liveliness like any other,
    # never restarts them
    external: list[str] = msgspec.field(default_factory=list)
    # resume: the env host's step counter starts after this, above every step number an earlier session may have used
    # (step logs are joined to episodes by step)
    resume_step: Annotated[int, Meta(ge=0)] | None = None

    # a role adopts step s only if last < s <= last + step_window (runtime/bounds.py): one message with an absurd step
    # cannot freeze it
    step_window: Annotated[int, Meta(ge=1)] = 10_000
    # a role that made progress and then none for this long logs a WARNING and reports 'stalled' in its heartbeat
    stall_warn_s: Annotated[float, Meta(gt=0)] = 30.0
    # the run is reported degraded when default actions or fallback messages exceed this fraction of agent x env-copy
    # steps
    degraded_fraction: Annotated[float, Meta(ge=0, le=1)] = 0.05
    # the run is reported degraded when the roles rejected more messages than this
    degraded_rejections: Annotated[int, Meta(ge=0)] = 0
    # the run is reported degraded when a role's liveliness token was gone longer than this at a time (a crashed agent
    # the launcher restarts is back in a few seconds)
    max_absence_s: Annotated[float, Meta(gt=0)] = 10.0
    # disk one process's per-step link log (RUN/linksteps/) may take: beyond half of it the file is rotated and the
    # one before dropped; episodes that began before the dropped steps get empty link columns in episode_links.csv
    step_log_max_mb: Annotated[float, Meta(gt=0)] = 64.0
    # trace=true: disk the env host's trace may take; beyond it the oldest steps are dropped (trace.npz keeps the
    # latest, its `steps` say which)
    trace_max_mb: Annotated[float, Meta(gt=0)] = 512.0
    # Zenoh's lease: a link silent this long is closed and made anew when it returns (None: Zenoh's 10 s; a fleet's
    # 1.2 s). Within the lease a link that comes back resumes at TCP's next retransmission, which backs off (0.2, 0.6,
    # 1.4, 3 s ...); past it, the link is opened anew (docs/fleet.md "Recovery")
    zenoh_lease_s: Annotated[float, Meta(ge=0.5)] | None = None
    # one attempt to open a link (TCP, TLS, Zenoh's handshake) is given up after this long and tried again (None:
    # Zenoh's 10 s; a fleet's: 0.5 s, docs/fleet.md)
    zenoh_open_timeout_s: Annotated[float, Meta(ge=0.1)] | None = None
    # the longest wait between tries to reach a lost hub or router (from 0.1 s, doubling; None: 0.5 s, a Zenoh config
    # file's own, a fleet's 0.1 s; Zenoh's own default backs off to 4 s)
    reconnect_max_s: Annotated[float, Meta(ge=0.1)] | None = None
    # size at which a role's log (RUN/logs/<role>.log) and the launcher's are rotated (<role>.log.1, .2; older ones
    # are deleted)
    log_max_mb: Annotated[float, Meta(gt=0)] = 10.0
    # local agents per process: 1 = one process each (what an edge device runs); k > 1 = pools of k agents, each pool
    # one process and one event loop (local_agent/pool.py); 0 = from the machine's cores (`hammer up` resolves it:
    # auto_agents_per_process)
    agents_per_process: Annotated[int, Meta(ge=0)] = 0

    # eval: 0 (default): the policy server publishes each version once and a role that joins late asks for it (a
    # query, over its own link only); > 0: it also republishes this long after a publish, then twice as long each time
    weights_republish_s: Annotated[float, Meta(ge=0)] = 0.0
    # eval: the policy server sends the weights as float16, half the bytes on every link (the agents compute in
    # float32; how many actions change: docs/deploy.md)
    weights_float16: bool = False
    # eval: observations, global states and central messages go on the wire as float16, half their bytes (read as
    # float32; what it does to the actions: `hammer bench wire BUNDLE`); never in training, whose results must be
    # float32 exactly
    wire_float16: bool = False
    # eval: the longest wait between republishes (the back-off's ceiling); set it to weights_republish_s for a fixed
    # period
    weights_republish_max_s: Annotated[float, Meta(gt=0)] = 16.0

    # eval: a pushed version reaches each local agent in chunks of this many bytes, each asked for by the agent once
    # per step, before its action (one outstanding per agent), so at most one chunk sits ahead of a link's step
    # traffic (512 B: 16 ms of a 256 kbit/s link; 1024 B left a few messages late there, docs/deploy.md); 0: the whole
    # weights are published at once
    weights_chunk_bytes: Annotated[int, Meta(ge=0, le=65536)] = 512
    # eval: the env host names a pushed version once every agent it is for holds it, or after this long regardless
    # (counted as push_named_unheld, logged)
    weights_name_timeout_s: Annotated[float, Meta(gt=0)] = 20.0

    def check(self) -> None:
        if 0 < self.weights_chunk_bytes < 64:
            raise ValueError(f"weights_chunk_bytes={self.weights_chunk_bytes}: a chunk of under 64 B costs more in "
                             "headers than it carries; fix: 64..65536 (512 suits a 256 kbit/s link), or 0 to publish "
                             "whole weights")
        for e in self.hub_listen:
            try:
                TransportConfig(listen=[e])
            except ValueError:
                raise ValueError(f"hub_listen: {e!r} is not an endpoint; fix: give one like tcp/192.0.2.1:7447 "
                                 "(this machine's address the agents reach, and a port)") from None
        if self.mode == "eval" and not self.policy_dir:
            raise ValueError("mode=eval needs policy_dir: the directory holding local.safetensors (e.g. RUN/final)")
        if self.wire_float16 and self.mode != "eval":
            raise ValueError("wire_float16=true is for serving (mode=eval): a training run must see float32 exactly")
        if self.secure and self.insecure:
            raise ValueError("secure=true and insecure=true contradict each other: pass one of --secure, --insecure")
        if self.hub_listen and self.zenoh_config_file:
            raise ValueError("hub_listen (--listen) and zenoh_config_file: the Zenoh config decides where the hub "
                             "listens; fix: pass one of them")
        if self.secure_hub and not self.secure:
            raise ValueError("secure_hub=true needs secure=true (it adds the router's identity to a secure run)")
        if (self.resume_from is None) != (self.resume_step is None):
            raise ValueError("resume_from and resume_step go together (both set by `hammer up --resume`)")
        if self.resume_from is not None and self.mode != "train":
            raise ValueError("resume_from: only a training run (mode=train) can be resumed")

    def refuse_plain_beyond_loopback(self, transport: TransportConfig, insecure: bool = False,
                                     fix: str = PLAIN_FIX) -> None:
        """Raise ValueError (one line) when `transport` reaches past this machine in the plain profile
        and neither this run nor the command (`insecure`) accepted that (CockroachDB's convention)."""
        refuse_plain_beyond_loopback(transport, self.secure, self.insecure or insecure, fix)

    def agent_groups(self, n_agents: int) -> list[list[int]]:
        """The local agents of each local-agent process `hammer up` starts, in order: chunks of
        `agents_per_process` (0 counts as 1 here: the launcher resolves it before saving) of the
        agents that are not external (an external agent is started by hand, alone)."""
        external = {int(m[1]) for e in self.external if (m := re.fullmatch(r"local-(\d+)", e))}
        agents = [i for i in range(n_agents) if i not in external]
        k = max(1, self.agents_per_process)
        return [agents[j:j + k] for j in range(0, len(agents), k)]

    def pools(self, n_agents: int) -> tuple[tuple[str, tuple[int, ...]], ...]:
        """The run's agent pools (groups of more than one agent): (pool name, agents); the secure
        profile gives each one identity granted exactly its agents' keys (protocol.access)."""
        from hammer.protocol.access import pool_name

        return tuple((pool_name(g), tuple(g)) for g in self.agent_groups(n_agents) if len(g) > 1)

    def link(self, transport: TransportConfig, fleet: bool = False) -> TransportConfig:
        """`transport` with this run's lease, open timeout and reconnect period (`zenoh_lease_s`,
        `zenoh_open_timeout_s`, `reconnect_max_s`); a Zenoh config file keeps its own retry periods
        unless `reconnect_max_s` is set here (unset: 0.5 s). `fleet`: a fleet's link, whose unset lease, open timeout
        and reconnect period are the fleet's (protocol.session.FLEET_LEASE_MS, FLEET_OPEN_TIMEOUT_MS or,
        for a client dialling over loopback, FLEET_LOOPBACK_OPEN_TIMEOUT_MS, FLEET_RECONNECT_MAX_MS)."""
        update: dict = {}
        if self.zenoh_lease_s is not None:
            update["lease_ms"] = round(self.zenoh_lease_s * 1000)
        elif fleet:
            update["lease_ms"] = FLEET_LEASE_MS
        if self.zenoh_open_timeout_s is not None:
            update["open_timeout_ms"] = round(self.zenoh_open_timeout_s * 1000)
        elif fleet:
            # over loopback no SYN is lost: an attempt waits for a stalled router's turn (protocol.session)
            loopback = bool(transport.connect) and all(is_loopback_endpoint(e) for e in transport.connect)
            update["open_timeout_ms"] = FLEET_LOOPBACK_OPEN_TIMEOUT_MS if loopback else FLEET_OPEN_TIMEOUT_MS
        if self.reconnect_max_s is not None:
            update["reconnect_max_ms"] = round(self.reconnect_max_s * 1000)
        elif fleet:
            update["reconnect_max_ms"] = FLEET_RECONNECT_MAX_MS
        return replace(transport, **update)

    def transport(self) -> TransportConfig:
        """Each role is a peer connecting to the hub; peers then meet directly (gossip), so the
        step loop has no extra router hop."""
        if self.zenoh_config_file:
            return self.link(TransportConfig(zenoh_config_file=self.zenoh_config_file))
        return self.link(TransportConfig(listen=["tcp/127.0.0.1:0"], connect=[loopback_endpoint(self.hub_port)]))

    def transport_to(self, connect: str, client: bool = False) -> TransportConfig:
        """A role joining the hub at `connect` by hand. A peer (lock-stepped runs): beyond loopback it
        listens on every interface: peers meet directly and the hub relays nothing between them, so
        the run's other roles must be able to reach it back (a role listening on its own loopback would
        hear only the hub). `client`: a Zenoh client of the router at `connect` (a fleet's roles and
        robots): it listens nowhere, nobody dials it, and the router carries all its traffic."""
        try:
            if client:
                return self.link(TransportConfig(mode="client", connect=[connect]), fleet=True)
            return self.link(TransportConfig(
                listen=["tcp/127.0.0.1:0" if is_loopback_endpoint(connect) else "tcp/0.0.0.0:0"], connect=[connect]))
        except ValueError:
            raise ValueError(f"--connect {connect!r}: not a Zenoh endpoint; fix: give the hub's address and port, "
                             "e.g. tcp/192.0.2.1:7447") from None

    def hub_transport(self) -> TransportConfig:
        if self.zenoh_config_file:
            return self.link(TransportConfig(zenoh_config_file=self.zenoh_config_file))
        return self.link(TransportConfig(listen=[loopback_endpoint(self.hub_port), *self.hub_listen]))

    @property
    def echo(self) -> bool:
        """Whether an action carries back the message it acted on: the env host records it in the
        rollout (training) and in a trace; serving needs neither, and the message stays off the
        wire (constrained links pay for every byte). The env host declares it (`Dims.echo`) and refuses an action without it."""
        return self.mode == "train" or self.trace

    @property
    def policy_role(self) -> str:
        """The name of the role that publishes the weights: `policy`, the policy server, in a served
        run (mode=eval), else `learner` (protocol.access.policy_role)."""
        from hammer.protocol.access import policy_role

        return policy_role(self.mode == "eval")

    def secured(self, transport: TransportConfig, role: str, run_dir: Path | None, n_agents: int, *,
                identity_directory: Path | None = None) -> TransportConfig:
        """`transport` as role `role` of a secure run: TLS endpoints, the role's identity from
        RUN/identity/ (or `identity_directory`: an edge agent's copy of its three files) and the run's
        access rules; unchanged when the run is not secure."""
        if not self.secure:
            return transport
        from hammer.protocol.access import secure_link, tls_endpoint
        from hammer.protocol.identity import identity_dir
        from hammer.protocol.keys import Keys

        where = identity_directory if identity_directory is not None else identity_dir(run_dir)
        return replace(transport, listen=[tls_endpoint(e) for e in transport.listen],
                       connect=[tls_endpoint(e) for e in transport.connect],
                       security=secure_link(where, role, Keys(self.run_id), n_agents, self.pools(n_agents),
                                            router=self.secure_hub))

    def save(self, run_dir: Path) -> None:
        # `secure`, `secure_hub`, `external` and the bounds are written only when set: a default runtime.json is what it always was.
        exclude = {f for f in ("secure", "secure_hub", "external", "hub_listen", *_BOUNDS)
                   if getattr(self, f) == default_of(type(self), f)}
        if self.agents_per_process <= 1:  # one agent per process: what a runtime.json without it means
            exclude.add("agents_per_process")
        (Path(run_dir) / "runtime.json").write_text(json.dumps(dump(self, exclude), indent=1, ensure_ascii=False))

    @classmethod
    def load(cls, run_dir: Path) -> RuntimeSettings:
        path = Path(run_dir) / "runtime.json"
        if not path.is_file():
            raise FileNotFoundError(f"{path} is missing: start roles with `hammer up`, or pass --run-dir of a run it made")
        return parse(cls, json.loads(path.read_text()))


def runtime_items(items, flag: str = "--runtime") -> dict:
    """`--runtime FIELD=VALUE` items as {field: value}, each value read as YAML (numbers, booleans,
    lists, as a config file's `runtime:` section says them); the one parser of them, for every command.
    ValueError naming the item on a malformed one."""
    out: dict = {}
    for item in items or ():
        key, eq, val = item.partition("=")
        key = key.strip()
        if not eq or not key:
            raise ValueError(f"{flag} {item!r}: expected FIELD=VALUE, e.g. msg_deadline_ms=20")
        if key == "num_envs":  # a config field, not a runtime setting: what users reach for first
            raise ValueError(f"{flag} {item!r}: num_envs is not a runtime setting; fix: pass --num-envs {val.strip()}")
        import yaml  # here only: an edge agent given no --runtime item never loads it

        out[key] = yaml.safe_load(val)
    return out


def settings_error(err: Exception, flag: str = "--runtime") -> str:
    """A RuntimeSettings validation error as one line naming the field, with did-you-mean for typos."""
    import difflib

    if not isinstance(err, SettingsError):
        return f"{flag}: {' '.join(str(err).split())}"
    fields = field_names(RuntimeSettings)
    if err.kind == "unknown":
        close = difflib.get_close_matches(err.field, fields, n=1)
        hint = f"did you mean '{close[0]}'?" if close else f"valid fields: {', '.join(fields)}"
        return f"{flag} {err.field}: unknown field; fix: {hint}"
    got = f" (got {err.value!r})" if err.value is not None else ""
    return f"{flag} {err.field or 'settings'}: {err.msg}{got}"


def build_settings(base: dict, items=(), *, fixed: dict | None = None, flag: str = "--runtime") -> RuntimeSettings:
    """The one way a command makes its RuntimeSettings: `base` (what the command and its config file
    decided), then the `--runtime` items over it, then `fixed` (what no item may change here).
    ValueError with one line naming each bad field."""
    try:
        return parse(RuntimeSettings, {**base, **runtime_items(items, flag), **(fixed or {})})
    except ValueError as e:
        raise ValueError(settings_error(e, flag)) from None


# env_spec.json: the task's dimensions, written by `hammer up` next to runtime.json; every role reads it.
def write_env_spec(run_dir: Path, spec) -> None:
    (Path(run_dir) / "env_spec.json").write_text(json.dumps(asdict(spec), indent=1))


def read_env_spec(run_dir: Path):
    from hammer.envs.base import EnvSpec

    path = Path(run_dir) / "env_spec.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: pass the --run-dir that `hammer up` created")
    d = json.loads(path.read_text())
    d["agent_ids"] = tuple(d["agent_ids"])
    return EnvSpec(**d)
