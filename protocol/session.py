"""The only place in hammer that opens Zenoh.

`HammerSession` wraps one Zenoh session of one run: typed publishing (stamps run, send time,
sequence number and sender), validated subscriptions, liveliness, and the seeded fault layer.

Rules it enforces (each one a way Zenoh loses or stalls messages otherwise):
- Multicast scouting is always off unless the user hands a Zenoh JSON5 config file; peers find
  each other through explicit `listen` / `connect` endpoints (tcp/127.0.0.1:PORT here).
- Must-arrive traffic uses reliable publishers with CongestionControl.BLOCK (DROP loses
  messages even on loopback). Loss is simulated only by our seeded fault layer.
- Zenoh callbacks run on Zenoh's threads: the subscriber callback only copies the payload bytes
  into a `queue.Queue`; decoding and validation happen in the consumer's `get()` / `drain()`.
- fork is unsafe (a forked child's inherited session delivers nothing, a new open can hang):
  start processes with multiprocessing "spawn" or as fresh interpreters and open the session
  inside each process. A session used from another pid than the one that opened it raises.
"""

from __future__ import annotations

import collections
import ipaddress
import itertools
import json
import logging
import os
import queue
import re
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal, Self

import msgspec
import zenoh
from hammer.protocol.access import SecureLink
from hammer.protocol.binding import check_key, sender_of
from hammer.protocol.codec import Expected, _expected_types, decode, encode
from hammer.protocol.dims import Dims
from hammer.protocol.errors import ProtocolError
from hammer.protocol.fault_injection import FaultInjector, FaultSpec
from hammer.protocol.keys import Keys
from hammer.protocol.schemas import Message
from hammer.protocol.structs import Meta, Settings

log = logging.getLogger(__name__)

_ENDPOINT_RE = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream)/\S+$")


# A burst of at least this many puts in a row (the env host's N observations, the central agent's N
# messages, a pool's actions) goes out batched: every put but the last is not express, so Zenoh may
# coalesce the puts to one peer into one batch and wake that peer once; the last put is express and
# flushes: the loop floor of many agents falls, that of three does not (`hammer bench loop-floor`,
# figures in docs/scale.md). Shorter bursts stay express.
BATCH_MIN = 5
CALLBACK_RELEASE_S = 2.0  # how long close() waits for Zenoh to let go of this session's callbacks
DECLARED_KEYS_ENV = "HAMMER_DECLARED_KEYS"  # a directory: each session writes the keys it declared there at close


def query_parameters(text: str) -> dict[str, str]:
    """A query's parameters (`v=3&i=0`) as a dict; nothing when they exceed what any hammer query
    sends (8 pairs of 32 characters): the asker is not trusted to be small."""
    pairs = [p.partition("=") for p in text.split("&") if p] if len(text) <= 8 * 66 else []
    if len(pairs) > 8 or any(len(k) > 32 or len(v) > 32 for k, _, v in pairs):
        return {}
    return {k: v for k, _, v in pairs}


def burst_express(j: int, n: int) -> bool:
    """Whether put j (0-based) of a burst of n puts is express (see BATCH_MIN)."""
    return n < BATCH_MIN or j == n - 1


def _quietly(undeclare: Any) -> None:
    """Undeclare at shutdown; an entity already gone with its session is not an error."""
    try:
        undeclare()
    except Exception as e:  # noqa: BLE001 - zenoh raises ZError for already-closed entities
        log.debug("undeclare at close: %s", e)


# How a session retries an endpoint it lost (or never reached): from 100 ms, doubling, at most every
# 500 ms, so a robot is back within about half a second of its link returning, even after the lease
# (Zenoh's 10 s default) expired and the session to the hub had to be made anew. Zenoh's own default
# backs off to 4 s. A --zenoh-config file keeps whatever it says (benchmarks/netns.client_config
# writes the same).
RECONNECT = {"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 2}

# A fleet's links (its router, roles and robots: docs/fleet.md "Recovery"). A link cut for longer
# than the lease is closed on both sides and the robot opens a new one, which takes a fraction of a
# second once the link is back; a cut within the lease is ridden out by TCP, whose retransmissions
# back off exponentially (about 0.2, 0.6, 1.4, 3, 6 s after the cut), so with Zenoh's 10 s lease a
# robot cut for 8 s waited up to seconds after its link returned for the next retransmission. With
# a lease under 1.4 s a cut link is either back by the retransmission at ~1.4 s or made anew. And
# one attempt to open a link is given up after FLEET_OPEN_TIMEOUT_MS (Zenoh: 10 s): an attempt
# started while the link was down has lost its SYN, whose retransmission comes 1 s, then 3 s later.
# The next attempt follows FLEET_RECONNECT_MAX_MS later (hammer's other runs: 500 ms), so one is
# under way when the robot's kernel next resolves the router's address (ARP, once a second by
# default while it cannot): what is left of a robot's return after a long cut is that timer's.
FLEET_LEASE_MS = 1200
FLEET_OPEN_TIMEOUT_MS = 500
# ...but not for a client that dials the router over loopback (the serving machine's own roles, and
# every robot of a fleet on one machine), where no SYN is ever lost and a short attempt only does
# harm: Zenoh's TLS listener sleeps 100 ms after every handshake that fails (its accept loop's
# throttle, a compile-time constant), so it takes at most 10 failed handshakes a second, first come
# first served. While the router is stalled (SIGSTOP, a starved CPU) the kernel still completes every
# connection, and each attempt given up after 0.5 s leaves a handshake that will fail: once six
# clients of one listener are retrying, every new attempt waits behind more than 0.5 s of dead ones,
# is given up in turn, and the router admits no one, for as long as the clients keep trying (robots
# stranded, docs/fleet.md "A stalled server"). An attempt that waits
# for its turn instead (Zenoh's own 10 s) is admitted as soon as the dead ones ahead of it are done.
FLEET_LOOPBACK_OPEN_TIMEOUT_MS = 10_000
FLEET_RECONNECT_MAX_MS = 100


def free_loopback_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (bind to port 0, read, release)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def loopback_endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def is_loopback_endpoint(endpoint: str) -> bool:
    """Whether a Zenoh endpoint (`tcp/127.0.0.1:7447`, `tls/[::1]:7447#iface=lo`) stays on this machine."""
    proto, _, addr = endpoint.partition("/")
    if proto.startswith("unixsock"):
        return True
    host = re.split(r"[#?]", addr, maxsplit=1)[0].rsplit(":", 1)[0].strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name: it may resolve anywhere


def _endpoint_list(raw: str, mode: str) -> list[str]:
    """Endpoints from a Zenoh config value: a list, or per mode {"router": [...], "peer": [...]}."""
    value = json.loads(raw)
    if isinstance(value, dict):
        value = value.get(mode, [])
    return list(value) if isinstance(value, list) else []


class TransportConfig(Settings):
    """How a process reaches the others.

    Default: a peer with no endpoints (talks to nobody). Typical loopback setup: one process
    `listen=["tcp/127.0.0.1:7447"]`, the others `connect=["tcp/127.0.0.1:7447"]`. For real
    deployments (router, client mode, TLS, auth) give `zenoh_config_file` (JSON5); then that file
    decides scouting too, and `mode` / `listen` / `connect` / `reconnect_max_ms` given here override it.
    """

    # None: the Zenoh config file's mode, else a peer
    mode: Literal["peer", "client", "router"] | None = None
    # endpoints to listen on, e.g. tcp/127.0.0.1:7447
    listen: list[str] = msgspec.field(default_factory=list)
    # Zenoh's lease: a link silent this long is closed (None: Zenoh's 10 s)
    lease_ms: Annotated[int, Meta(ge=500)] | None = None
    # the longest wait between tries to reach a lost endpoint (None: the Zenoh config file's, else 500 ms)
    reconnect_max_ms: Annotated[int, Meta(ge=100)] | None = None
    # one attempt to open a link is given up after this long (None: Zenoh's 10 s)
    open_timeout_ms: Annotated[int, Meta(ge=100)] | None = None
    # endpoints to connect to
    connect: list[str] = msgspec.field(default_factory=list)
    # Zenoh JSON5 config for real deployments (a Path is taken too)
    zenoh_config_file: str | None = None
    # mutual TLS identity + access rules (protocol.access)
    security: SecureLink | None = None
    # Zenoh's shared memory with peers on this machine (None: Zenoh's default, on: a put over 3 KB to a local
    # peer goes through a 16 MB pool this process maps); an edge agent turns it off (serve/edge_entry.py): 16 MB of
    # its RSS on loopback, nothing across machines
    shared_memory: bool | None = None

    def __post_init__(self) -> None:
        if isinstance(self.zenoh_config_file, Path):
            self.zenoh_config_file = str(self.zenoh_config_file)
        super().__post_init__()

    def check(self) -> None:
        for e in (*self.listen, *self.connect):
            if not _ENDPOINT_RE.match(e):
                raise ValueError(f"endpoint {e!r} must look like 'tcp/127.0.0.1:7447' (protocol/address:port)")
        if self.zenoh_config_file is None and self.mode == "client" and not self.connect:
            raise ValueError("mode 'client' needs at least one connect endpoint (the router's address)")
        if self.zenoh_config_file is not None and not Path(self.zenoh_config_file).is_file():
            raise ValueError(f"zenoh_config_file {self.zenoh_config_file!r} does not exist")

    @classmethod
    def listener(cls, port: int | None = None) -> TransportConfig:
        """A peer listening on 127.0.0.1:port (a free port if None)."""
        return cls(listen=[loopback_endpoint(port or free_loopback_port())])

    @classmethod
    def connector(cls, port: int) -> TransportConfig:
        """A peer connecting to 127.0.0.1:port."""
        return cls(connect=[loopback_endpoint(port)])

    def beyond_loopback(self) -> list[str]:
        """What of this transport reaches past this machine: every listen or connect endpoint that is
        not a loopback address (0.0.0.0 and host names included), and multicast scouting when a
        Zenoh config file leaves it on. Empty for a loopback-only transport."""
        if self.zenoh_config_file is None:
            listen, connect, multicast = self.listen, self.connect, False
        else:
            cfg = self.to_zenoh()
            mode = json.loads(cfg.get_json("mode"))
            listen, connect = (_endpoint_list(cfg.get_json(f"{k}/endpoints"), mode) for k in ("listen", "connect"))
            if mode == "client":
                listen = []  # a client only connects
            multicast = json.loads(cfg.get_json("scouting/multicast/enabled")) is not False
        out = [e for e in [*listen, *connect] if not is_loopback_endpoint(e)]
        return out + (["multicast scouting"] if multicast else [])

    def to_zenoh(self) -> zenoh.Config:
        if self.zenoh_config_file is not None:
            cfg = zenoh.Config.from_file(self.zenoh_config_file)
            if self.mode is not None:
                cfg.insert_json5("mode", json.dumps(self.mode))
        else:
            cfg = zenoh.Config()
            cfg.insert_json5("mode", json.dumps(self.mode or "peer"))
            cfg.insert_json5("scouting/multicast/enabled", "false")
            # A router stamps every sample it relays with its clock and id (~26 B a message) unless told
            # not to; hammer reads no Zenoh timestamp (a receiver dates a message by its arrival), and on
            # a fleet robot's link those bytes were a quarter of each observation's packet.
            cfg.insert_json5("timestamping/enabled", "false")
        if self.listen or self.zenoh_config_file is None:
            cfg.insert_json5("listen/endpoints", json.dumps(self.listen))
        if self.connect or self.zenoh_config_file is None:
            cfg.insert_json5("connect/endpoints", json.dumps(self.connect))
        if self.zenoh_config_file is None or self.reconnect_max_ms is not None:
            most = self.reconnect_max_ms or RECONNECT["period_max_ms"]
            cfg.insert_json5("connect/retry", json.dumps({**RECONNECT, "period_max_ms": most,
                                                          "period_init_ms": min(RECONNECT["period_init_ms"], most)}))
        if self.shared_memory is not None:
            cfg.insert_json5("transport/shared_memory/enabled", json.dumps(self.shared_memory))
        if self.lease_ms is not None:
            cfg.insert_json5("transport/link/tx/lease", str(self.lease_ms))
        if self.open_timeout_ms is not None:
            cfg.insert_json5("transport/unicast/open_timeout", str(self.open_timeout_ms))
        if self.security is not None:
            self.security.apply(cfg)
        return cfg


# --------------------------------------------------------------------------------------------
# Subscriptions
# --------------------------------------------------------------------------------------------


QUEUE_DEPTH = 256  # payloads held per key by default before the newest are dropped (see _QueueSub)
KEYS_TRACKED = 64  # (key, reason) pairs a subscription tallies its refusals under (SubscriptionStats.by_key)


@dataclass
class SubscriptionStats:
    """received: payloads taken off the queue; delivered: valid messages returned;
    rejected: invalid payloads per reason (size, decode, version, type, field, dtype, shape,
    nonfinite, range, checksum, run, key_mismatch); overflow: payloads dropped because their key's
    queue was full. An oversize payload is counted (`size`) on arrival, without being copied or queued."""

    received: int = 0
    delivered: int = 0
    overflow: int = 0
    decode_s: float = 0.0  # wall time in decode + validation (hammer bench scale: where a step's time goes)
    rejected: collections.Counter = field(default_factory=collections.Counter)
    # refusals (overflow included) per (key, reason): which robot's keys a flood or a forgery came on,
    # so a verdict can name the key that was attacked; at most KEYS_TRACKED keys, the rest as "*"
    by_key: collections.Counter = field(default_factory=collections.Counter)

    def refused(self, key: str, reason: str) -> None:
        if reason == "overflow":
            self.overflow += 1
        else:
            self.rejected[reason] += 1
        if (key, reason) not in self.by_key and len(self.by_key) >= KEYS_TRACKED:
            key = "*"  # a wildcard subscription may see keys without end in a plain run: the tally stays bounded
        self.by_key[(key, reason)] += 1

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())


class _QueueSub:
    """Shared part: a Zenoh subscriber whose callback only enqueues raw bytes with their key.

    Intake is bounded before anything is decoded, so a flood on one key costs the receiver neither
    memory nor step time: a payload over the size cap is refused on arrival without a copy (`size`),
    and each key (a wildcard subscription covers several, e.g. every agent's actions) may hold at
    most `maxsize` payloads not yet taken; beyond that the newest is dropped and counted
    (`overflow`). Dropping the newest keeps one FIFO per subscription, so a flooded key can put at
    most `maxsize` payloads ahead of another key's, and a key that floods loses its own messages,
    nobody else's."""

    cap: int | None = None  # payloads longer than this are rejected on arrival (None: no cap)

    def __init__(self, key_expr: str, maxsize: int, inbox: Inbox | None = None) -> None:
        self.key_expr = key_expr
        self.stats = SubscriptionStats()
        # SimpleQueue, not Queue: put and get(timeout) run in C without Python-level locks and
        # conditions, so the Zenoh thread holds the GIL for less time and the consumer wakes sooner.
        self._q: queue.SimpleQueue[tuple[str, bytes]] = queue.SimpleQueue()
        self._maxsize = maxsize
        self._pending: collections.Counter[str] = collections.Counter()  # per key: queued, not yet taken
        self._pending_lock = threading.Lock()
        self._zsub: Any = None
        self._inbox = inbox  # when set, payloads go into that shared queue, tagged with this subscription

    def _on_sample(self, sample: zenoh.Sample) -> None:
        # Runs on a Zenoh thread: copy the bytes out and return; never decode or block here.
        if self.cap is not None and (n := len(sample.payload)) > self.cap:
            self.stats.refused(str(sample.key_expr), "size")  # Counter updates: atomic enough under the GIL
            if self.stats.rejected["size"] <= 10:
                log.warning("rejected oversize message (%d bytes, cap %d) on %s", n, self.cap, sample.key_expr)
            return
        key = str(sample.key_expr)
        if self._maxsize:
            with self._pending_lock:
                full = self._pending[key] >= self._maxsize
                if not full:
                    self._pending[key] += 1
            if full:
                self.stats.refused(key, "overflow")
                if self.stats.overflow <= 10 or self.stats.overflow % 1000 == 0:
                    log.warning("queue of %s full (%d): dropped the newest payload (#%d)", key, self._maxsize,
                                self.stats.overflow)
                return
        if self._inbox is None:
            self._q.put((key, sample.payload.to_bytes()))
        else:
            self._inbox.q.put((self, key, sample.payload.to_bytes()))

    def _taken(self, key: str) -> None:
        """The consumer took one payload of `key` off the queue."""
        if self._maxsize:
            with self._pending_lock:
                left = self._pending[key] - 1
                if left > 0:
                    self._pending[key] = left
                else:
                    del self._pending[key]

    def pending(self) -> int:
        return self._q.qsize() if self._inbox is None else self._inbox.q.qsize()

    def close(self) -> None:
        if self._zsub is not None:
            _quietly(self._zsub.undeclare)
            self._zsub = None


class RawSubscription(_QueueSub):
    """Raw payload bytes, for benchmarks and tools; no validation."""

    def get(self, timeout: float | None = None) -> bytes | None:
        try:
            key, data = self._q.get(timeout=timeout) if timeout != 0 else self._q.get_nowait()
        except queue.Empty:
            return None
        self._taken(key)
        self.stats.received += 1
        self.stats.delivered += 1
        return data


class Subscription(_QueueSub):
    """Validated messages of the expected type(s) from one key expression.

    `get()` / `drain()` decode in the caller's thread. Invalid payloads are counted in
    `stats.rejected[reason]` and logged, never raised: the next valid message is delivered. Every
    message delivered says what its key says (protocol.binding.check_key). The size cap is the
    smallest of `max_bytes`, the expected types' caps and, where `dims` declares every size of the
    type, what a valid message of those sizes can weigh (`Message.cap_for`).
    """

    def __init__(self, key_expr: str, expected: Expected, dims: Dims | None, run: str,
                 maxsize: int, max_bytes: int | None, inbox: Inbox | None = None) -> None:
        super().__init__(key_expr, maxsize, inbox)
        self.expected, self.dims, self.run, self.max_bytes = expected, dims, run, max_bytes
        self._prefix_len = len(Keys(run).prefix) + 1
        types = _expected_types(expected)
        if max_bytes is not None:
            self.cap = max_bytes
        else:
            caps = [t.cap_for_dims(dims) if dims is not None else t.MAX_BYTES for t in types]
            self.cap = max(caps)

    def _decode(self, key: str, data: bytes) -> Message | None:
        self._taken(key)
        self.stats.received += 1
        t0 = time.perf_counter()
        try:
            msg = decode(data, self.expected, max_bytes=self.max_bytes)
            check_key(msg, key[self._prefix_len:])  # who it claims to be, before what it declares
            if self.dims is not None:
                msg.check_dims(self.dims)
        except ProtocolError as e:
            self.stats.decode_s += time.perf_counter() - t0
            self.stats.refused(key, e.reason)
            n = self.stats.rejected[e.reason]
            if n <= 10 or n % 1000 == 0:
                log.warning("rejected message #%d (%s) on %s: %s%s", n, e.reason, self.key_expr, e,
                            "" if key == self.key_expr else f" (key {key})")
            return None
        self.stats.decode_s += time.perf_counter() - t0
        self.stats.delivered += 1
        return msg

    def get(self, timeout: float | None = None) -> Message | None:
        """The next valid message, waiting up to `timeout` s (None = forever, 0 = no wait);
        None if none arrived in time."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            try:
                if deadline is None:
                    key, data = self._q.get()
                else:
                    remaining = deadline - time.monotonic()
                    key, data = self._q.get(timeout=remaining) if remaining > 0 else self._q.get_nowait()
            except queue.Empty:
                return None
            msg = self._decode(key, data)
            if msg is not None:
                return msg

    def drain(self, max_items: int | None = None) -> list[Message]:
        """Every valid message already queued (without waiting)."""
        out: list[Message] = []
        while max_items is None or len(out) < max_items:
            try:
                key, data = self._q.get_nowait()
            except queue.Empty:
                break
            msg = self._decode(key, data)
            if msg is not None:
                out.append(msg)
        return out


class LatestSubscription(Subscription):
    """The newest payload of each key only, with the time it arrived: for streams where only the
    freshest message counts and its age is what a receiver decides on (a fleet's central messages,
    uplinks and actions). A payload that arrives before the previous one of its key was taken
    replaces it (counted as `superseded`), so a receiver that was busy or paused never works through
    a backlog of old messages, and memory stays one payload per key."""

    def __init__(self, key_expr: str, expected: Expected, dims: Dims | None, run: str,
                 max_bytes: int | None) -> None:
        super().__init__(key_expr, expected, dims, run, 0, max_bytes)
        self._slots: dict[str, tuple[bytes, float]] = {}
        self._slot_lock = threading.Lock()
        self._arrived = threading.Event()
        self.superseded = 0

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if self.cap is not None and (n := len(sample.payload)) > self.cap:
            self.stats.refused(str(sample.key_expr), "size")
            if self.stats.rejected["size"] <= 10:
                log.warning("rejected oversize message (%d bytes, cap %d) on %s", n, self.cap, sample.key_expr)
            return
        item = (sample.payload.to_bytes(), time.monotonic())
        key = str(sample.key_expr)
        with self._slot_lock:
            if key in self._slots:
                self.superseded += 1
            self._slots[key] = item
        self._arrived.set()

    def wait(self, timeout: float) -> bool:
        """Block until a payload is waiting (True) or `timeout` s pass (False)."""
        return self._arrived.wait(timeout)

    def take(self) -> list[tuple[Message, float]]:
        """(message, arrival time on time.monotonic()) of every key that has a new valid one."""
        with self._slot_lock:
            slots, self._slots = self._slots, {}
            self._arrived.clear()
        out = []
        for key, (data, t) in slots.items():
            msg = self._decode(key, data)
            if msg is not None:
                out.append((msg, t))
        return out

    def pending(self) -> int:
        return len(self._slots)


class Inbox:
    """One queue fed by many subscriptions: a process serving many agents (an agent pool) waits on
    all their inputs at once in one thread, instead of one thread or one poll per subscription.

    Each payload is queued with the subscription it came from and is decoded and validated by that
    subscription (its own dims, size cap, queue bound and rejection counters), in the consumer's thread."""

    def __init__(self) -> None:
        self.q: queue.SimpleQueue[tuple[Subscription, str, bytes]] = queue.SimpleQueue()

    def get(self, timeout: float | None = None) -> tuple[Subscription, Message] | None:
        """The next valid message and its subscription, waiting up to `timeout` s (0: no wait)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            try:
                if deadline is None:
                    sub, key, data = self.q.get()
                else:
                    remaining = deadline - time.monotonic()
                    sub, key, data = self.q.get(timeout=remaining) if remaining > 0 else self.q.get_nowait()
            except queue.Empty:
                return None
            msg = sub._decode(key, data)
            if msg is not None:
                return sub, msg


@dataclass(frozen=True)
class AliveEvent:
    role: str
    alive: bool


class LivelinessWatch:
    """Roles appearing (token declared) and disappearing (undeclared, closed or killed)."""

    def __init__(self, keys: Keys) -> None:
        self._keys = keys
        self._q: queue.Queue[AliveEvent] = queue.Queue()
        self._zsub: Any = None

    def _on_sample(self, sample: zenoh.Sample) -> None:
        role = self._keys.role_of_alive_key(str(sample.key_expr))
        self._q.put_nowait(AliveEvent(role, sample.kind == zenoh.SampleKind.PUT))

    def get(self, timeout: float | None = None) -> AliveEvent | None:
        try:
            return self._q.get(timeout=timeout) if timeout != 0 else self._q.get_nowait()
        except queue.Empty:
            return None

    def drain(self) -> list[AliveEvent]:
        out = []
        while (e := self.get(0)) is not None:
            out.append(e)
        return out

    def close(self) -> None:
        if self._zsub is not None:
            _quietly(self._zsub.undeclare)
            self._zsub = None


# --------------------------------------------------------------------------------------------
# Publishing
# --------------------------------------------------------------------------------------------


class Publisher:
    """Publishes typed messages (or raw bytes) on one key, through the fault layer if any."""

    def __init__(self, session: HammerSession, key: str, zpub: zenoh.Publisher) -> None:
        self.key = key
        self._session = session
        self._zpub = zpub
        self._rel = session.keys.relative(key)
        # The sender a key implies goes as "" (the receiver takes it from the key, protocol.binding);
        # on a key that implies none (ctl/all, bench/...) the session's own name.
        self._stamp = {"sender": "" if sender_of(self._rel) else session.sender}
        self._seq = itertools.count()
        self._lock = threading.Lock()
        self.faults = session.faults  # an agent pool gives each agent's publishers that agent's own injector
        self.max_bytes: int | None = None  # a size cap other than the message type's (a large run's rollout chunk)
        # float32 observations and messages as float16 on the wire (opt-in: codec.encode(half=True))
        self.half = session.wire_float16
        self.sent_msgs = 0  # payloads handed to the fault layer / Zenoh (hammer bench scale: messages per step)
        self.sent_bytes = 0
        self.encode_s = 0.0  # wall time stamping + encoding, and in the put (fault layer + Zenoh)
        self.put_s = 0.0

    def publish(self, msg: Message) -> int:
        """Stamp the sender (the one the key implies, protocol.binding), encode and send;
        returns the seq used."""
        t0 = time.perf_counter()
        seq, data = self.stamped(msg)
        t1 = time.perf_counter()
        self.put_bytes(data)
        self.encode_s += t1 - t0
        self.put_s += time.perf_counter() - t1
        return seq

    def stamped(self, msg: Message) -> tuple[int, bytes]:
        """(seq, bytes) of `msg` stamped as this key's next message (the sender the key implies,
        protocol.binding) and encoded: what `publish` sends, and what an answer to a query on this
        key carries. seq counts this publisher's messages (kept here, not sent: a receiver orders
        the step loop by `step`)."""
        with self._lock:
            seq = next(self._seq)
        return seq, encode(msg, stamp=self._stamp, max_bytes=self.max_bytes, half=self.half)

    def put_bytes(self, data: bytes) -> None:
        self.sent_msgs += 1
        self.sent_bytes += len(data)
        faults = self.faults
        if faults is None:
            self._zpub.put(data)
        else:
            faults.submit(self._rel, data, self._zpub.put)

    def close(self) -> None:
        _quietly(self._zpub.undeclare)


def io_counters(pubs: list[Publisher], subs: list[Subscription]) -> dict[str, int | float]:
    """tx_msgs, tx_bytes, rx_msgs and the seconds in encode, put and decode (+ validation) of these."""
    return {"tx_msgs": sum(p.sent_msgs for p in pubs), "tx_bytes": sum(p.sent_bytes for p in pubs),
            "rx_msgs": sum(s.stats.received for s in subs),
            "encode_s": round(sum(p.encode_s for p in pubs), 4), "put_s": round(sum(p.put_s for p in pubs), 4),
            "decode_s": round(sum(s.stats.decode_s for s in subs), 4)}


class HammerSession:
    """One process's Zenoh session for one run. Use as a context manager; open it in the process
    that uses it (spawn-safe, never fork)."""

    def __init__(self, run_id: str, transport: TransportConfig | None = None,
                 faults: FaultSpec | None = None, sender: str | None = None) -> None:
        self.keys = Keys(run_id)
        self.run_id = run_id
        self.transport = transport or TransportConfig()
        self.sender = sender or f"pid{os.getpid()}"
        # Publishers made from now on send float32 observations and messages as float16 (opt-in,
        # serving: RuntimeSettings.wire_float16; codec.encode(half=True)).
        self.wire_float16 = False
        self.faults = FaultInjector(faults) if faults is not None and faults.enabled else None
        self._z: zenoh.Session | None = None
        self._pid: int | None = None
        self._publishers: dict[tuple[str, bool, bool], Publisher] = {}
        self._subs: list[Any] = []
        self._tokens: list[Any] = []
        self._queryables: list[Any] = []
        # One event per callback handed to Zenoh, set when Zenoh releases it. close() waits for them:
        # a Zenoh thread that calls into Python after the interpreter has begun to finalize aborts
        # the process ("FATAL: exception not rethrown"), so no callback may outlive the session.
        self._released: list[threading.Event] = []
        self._lock = threading.Lock()
        # What this session declared: (publish | subscribe | query | answer | alive | watch, key expression).
        # With HAMMER_DECLARED_KEYS=DIR each session writes it to DIR at close: an audit of what a run's
        # processes use against its access rules (tests/test_key_table.py; docs/security.md).
        self.declared: set[tuple[str, str]] = set()

    # ---- lifecycle -------------------------------------------------------------------------

    def open(self) -> Self:
        if self._z is None:
            self._z = zenoh.open(self.transport.to_zenoh())
            self._pid = os.getpid()
        return self

    def __enter__(self) -> Self:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __getstate__(self) -> None:
        raise TypeError("HammerSession cannot be pickled or sent to another process: "
                        "pass the run id and TransportConfig and open a session there")

    def close(self) -> None:
        """Flush the fault layer, undeclare everything and close the Zenoh session."""
        if self._z is None:
            return
        self._write_declared()
        if self.faults is not None:
            self.faults.close()
        for s in self._subs:
            s.close()
        for t in [*self._tokens, *self._queryables]:
            _quietly(t.undeclare)
        for p in self._publishers.values():
            p.close()
        self._subs.clear()
        self._tokens.clear()
        self._queryables.clear()
        self._publishers.clear()
        self._z.close()
        self._z = None
        deadline = time.monotonic() + CALLBACK_RELEASE_S
        for released in self._released:
            if not released.wait(max(deadline - time.monotonic(), 0.0)):
                log.warning("a Zenoh callback was still held %.0f s after the session closed", CALLBACK_RELEASE_S)
                break
        self._released.clear()

    def _handler(self, callback: Callable[[Any], None]) -> zenoh.handlers.Callback:
        """`callback` as Zenoh's handler, with the event close() waits for when Zenoh lets it go."""
        released = threading.Event()
        self._released = [e for e in self._released if not e.is_set()]
        self._released.append(released)
        return zenoh.handlers.Callback(callback, released.set)

    def _write_declared(self) -> None:
        directory = os.environ.get(DECLARED_KEYS_ENV)
        if not directory:
            return
        try:
            path = Path(directory) / f"{self.sender}-{os.getpid()}-{id(self)}.json"
            path.write_text(json.dumps({"sender": self.sender, "run": self.run_id,
                                        "declared": sorted(self.declared)}))
        except OSError as e:  # an audit aid: never what stops a role
            log.warning("could not write the declared keys to %s: %s", directory, e)

    @property
    def zenoh(self) -> zenoh.Session:
        if self._z is None:
            raise RuntimeError("session is not open: use `with HammerSession(...) as s:` or call open()")
        if self._pid != os.getpid():
            raise RuntimeError(f"session opened in pid {self._pid} used in pid {os.getpid()}: fork is unsafe, "
                               "open a new session inside each process (multiprocessing 'spawn')")
        return self._z

    def _own(self, key: str) -> str:
        self.keys.relative(key)  # raises if the key is not under hammer/<run>/
        return key

    # ---- publish ---------------------------------------------------------------------------

    def publisher(self, key: str, reliable: bool = True, express: bool = False,
                  block: bool | None = None) -> Publisher:
        """A (cached) publisher on `key`. reliable=True: RELIABLE + CongestionControl.BLOCK, for
        everything that must arrive; reliable=False: BEST_EFFORT + DROP (telemetry only).
        block=False with reliable=True: RELIABLE + DROP, for a stream where the freshest message is
        what counts and a dead link must never hold up the sender (a fleet's control streams:
        with BLOCK, one robot's cut link backs up into the publisher and stalls everyone)."""
        self._own(key)
        self.declared.add(("publish", key))
        block = reliable if block is None else block
        with self._lock:
            pub = self._publishers.get((key, reliable, express, block))
            if pub is None:
                zpub = self.zenoh.declare_publisher(
                    key,
                    congestion_control=zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP,
                    reliability=zenoh.Reliability.RELIABLE if reliable else zenoh.Reliability.BEST_EFFORT,
                    express=express,
                )
                pub = self._publishers[(key, reliable, express, block)] = Publisher(self, key, zpub)
        return pub

    def publish(self, key: str, msg: Message) -> int:
        """Publish a typed message reliably on `key`; returns its seq."""
        return self.publisher(key).publish(msg)

    def put_bytes(self, key: str, data: bytes) -> None:
        """Publish raw bytes reliably (benchmarks, malformed-input tests)."""
        self.publisher(key).put_bytes(data)

    # ---- subscribe -------------------------------------------------------------------------

    def subscribe(self, key_expr: str, expected: Expected = None, dims: Dims | None = None, *,
                  maxsize: int = QUEUE_DEPTH, max_bytes: int | None = None, inbox: Inbox | None = None) -> Subscription:
        """Validated messages of type(s) `expected` on `key_expr` (wildcards allowed).
        maxsize: payloads each key may queue before the newest are dropped and counted (overflow);
        0: unbounded (only for a consumer that never falls behind by design).
        inbox: deliver into that shared queue (`Inbox.get`) instead of this subscription's own."""
        sub = Subscription(self._own(key_expr), expected, dims, self.run_id, maxsize, max_bytes, inbox)
        self.declared.add(("subscribe", key_expr))
        sub._zsub = self.zenoh.declare_subscriber(key_expr, self._handler(sub._on_sample))
        self._subs.append(sub)
        return sub

    def subscribe_latest(self, key_expr: str, expected: Expected = None, dims: Dims | None = None, *,
                         max_bytes: int | None = None) -> LatestSubscription:
        """The newest valid message of each key on `key_expr` with its arrival time (`take()`)."""
        sub = LatestSubscription(self._own(key_expr), expected, dims, self.run_id, max_bytes)
        self.declared.add(("subscribe", key_expr))
        sub._zsub = self.zenoh.declare_subscriber(key_expr, self._handler(sub._on_sample))
        self._subs.append(sub)
        return sub

    # ---- ask for the current message (queries) --------------------------------------------

    def answer(self, key: str, current: Callable[..., Message | list[Message] | None], *,
               parameters: bool = False) -> None:
        """Answer every query on `key` (a Zenoh queryable) with `current()`, stamped as this session's
        publisher of `key` stamps (None: nothing to say yet; a list: one reply each, e.g. the two
        policy versions of a staged rollout). Why: a role that joins late asks for what it missed
        (the policy), so the copy crosses its own link only, instead of everyone receiving a
        republish. `current` runs on a Zenoh thread: it must only hand over what it has.
        parameters=True: `current(params)` gets the query's parameters (`key?v=3&i=0`) as a dict of
        strings, untrusted (the asker chose them): at most 8, each name and value at most 32 characters."""
        published = ("publish", key) in self.declared
        pub = self.publisher(key)  # its stamp only: a reply is not a publication
        if not published:
            self.declared.discard(("publish", key))
        self.declared.add(("answer", key))

        def on_query(query: zenoh.Query) -> None:
            msgs = current(query_parameters(str(query.parameters))) if parameters else current()
            for msg in msgs if isinstance(msgs, list) else [msgs]:
                if msg is not None:
                    query.reply(key, pub.stamped(msg)[1])

        self._queryables.append(self.zenoh.declare_queryable(self._own(key), self._handler(on_query)))

    def fetch(self, key: str, into: Subscription, timeout: float = 2.0, parameters: str = "") -> None:
        """Ask whoever answers `key` for its current message; returns at once. Each reply goes through
        `into`'s intake exactly as a published sample of its key would (size cap, queue bound, then
        decode, validation and key binding in the consumer's thread), so a reply is trusted no more
        than a publication. `parameters`: what to ask for (`v=3&i=0`: a chunk of a pushed version)."""

        def on_reply(reply: zenoh.Reply) -> None:
            ok = reply.ok
            if ok is not None:
                into._on_sample(ok)

        self.declared.add(("query", key))
        self.zenoh.get(self._own(key) + (f"?{parameters}" if parameters else ""), self._handler(on_reply),
                       timeout=timeout)

    def subscribe_raw(self, key_expr: str, *, maxsize: int = QUEUE_DEPTH) -> RawSubscription:
        sub = RawSubscription(self._own(key_expr), maxsize)
        self.declared.add(("subscribe", key_expr))
        sub._zsub = self.zenoh.declare_subscriber(key_expr, self._handler(sub._on_sample))
        self._subs.append(sub)
        return sub

    # ---- liveliness ------------------------------------------------------------------------

    def declare_alive(self, role: str) -> Any:
        """Declare this process's liveliness token `hammer/<run>/alive/<role>`. It disappears
        when undeclared, when the session closes, or when the process dies."""
        token = self.zenoh.liveliness().declare_token(self.keys.alive(role))
        self.declared.add(("alive", self.keys.alive(role)))
        self._tokens.append(token)
        return token

    def watch_alive(self, history: bool = True) -> LivelinessWatch:
        """Events for every role of this run going alive / dead (history: also those already alive)."""
        watch = LivelinessWatch(self.keys)
        self.declared.add(("watch", self.keys.alive("**")))
        watch._zsub = self.zenoh.liveliness().declare_subscriber(
            self.keys.alive("**"), self._handler(watch._on_sample), history=history
        )
        self._subs.append(watch)
        return watch

    def alive_roles(self, timeout: float = 1.0) -> set[str]:
        """Roles of this run whose liveliness token is currently declared."""
        self.declared.add(("watch", self.keys.alive("**")))
        replies = self.zenoh.liveliness().get(self.keys.alive("**"), timeout=timeout)
        roles = set()
        for reply in replies:
            if reply.ok is not None:
                roles.add(self.keys.role_of_alive_key(str(reply.ok.key_expr)))
        return roles

    def rejection_counts(self) -> dict[str, int]:
        """Payloads this session's subscriptions refused, by reason (`overflow`: dropped, queue full)."""
        total: collections.Counter[str] = collections.Counter()
        for sub in self._subs:
            stats = getattr(sub, "stats", None)
            if isinstance(sub, Subscription) and stats is not None:
                total.update(stats.rejected)
                if stats.overflow:
                    total["overflow"] += stats.overflow
        return dict(total)

    def rejections_by_key(self) -> dict[str, dict[str, int]]:
        """Payloads this session's subscriptions refused, per key (without the run's prefix) and
        reason: {"agent/act/1": {"size": 12}}; keys beyond what a subscription tallies as "*"."""
        out: dict[str, collections.Counter[str]] = {}
        skip = len(self.keys.prefix) + 1
        for sub in self._subs:
            stats = getattr(sub, "stats", None)
            if isinstance(sub, Subscription) and stats is not None:
                for (key, reason), n in list(stats.by_key.items()):
                    out.setdefault(key[skip:] if key != "*" else key, collections.Counter())[reason] += n
        return {k: dict(v) for k, v in out.items()}

    def fault_report(self) -> dict[str, dict[str, int]]:
        return self.faults.report() if self.faults is not None else {}

    def traffic(self) -> dict[str, int | float]:
        """What this session's publishers sent (before faults) and its subscriptions took in, and the
        wall time spent encoding, putting and decoding + validating (`hammer bench scale`)."""
        with self._lock:
            pubs = list(self._publishers.values())
        return io_counters(pubs, [s for s in self._subs if isinstance(s, Subscription)])


class OpenTimeout(ConnectionError):
    """`open_retrying` gave up at its deadline; `reason` is Zenoh's, in one line."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def open_retrying(make: Callable[[], HammerSession], deadline: float | None, stopped: Callable[[], bool],
                  on_wait: Callable[[str], None] | None = None, *, pause: Callable[[float], Any] = time.sleep,
                  retry_s: float = 1.0, log_every_s: float = 10.0) -> HammerSession | None:
    """The session `make()` builds, opened as soon as it can be: a client-mode config fails to open
    while its router is down (zenoh.ZError), so an agent started before its hub or router tries
    again every `retry_s` (waiting with `pause`, which may return early on a stop), calling
    `on_wait(reason)` at most every `log_every_s`. None once `stopped()`; OpenTimeout past
    `deadline` (time.monotonic; None: never)."""
    next_log = 0.0
    while not stopped():
        session = make()
        try:
            return session.open()
        except zenoh.ZError as e:
            reason = str(e).split(" at ", 1)[0].strip()
            now = time.monotonic()
            if deadline is not None and now > deadline:
                raise OpenTimeout(reason) from None
            if on_wait is not None and now >= next_log:
                on_wait(reason)
                next_log = now + log_every_s
            pause(retry_s)
    return None
