"""Seeded fault injection on the publish side: drop, duplicate, delay (with jitter), reorder.

Why our own layer: Zenoh on loopback is (with BLOCK) lossless and fast, so robustness to late,
lost, duplicated or reordered messages can only be tested if we make those faults ourselves,
reproducibly. Off by default: a session without a FaultSpec (or with no rules) sends directly.

Rules match keys *relative to the run prefix* (`agent/act/*`, `central/msg/**`, `**`) with Zenoh
wildcards: `*` is exactly one key chunk, `**` is zero or more chunks. The first rule that matches
a key applies to it. Each (rule, key) pair has its own RNG seeded from (spec seed, rule index, key),
and every message draws the same four numbers whatever happens to it, so the faults depend only on
the seed and on the order of messages on that key, never on wall-clock timing or on other keys.

Per message, in order: drop with probability `drop`; otherwise send `1 + duplicate?` copies, after
`delay_ms + uniform(-jitter_ms, +jitter_ms)` (clipped at 0); with probability `reorder` the message
is held back until `reorder_window` later messages on the same key have gone out (or
`reorder_max_hold_ms` passed, or the session closes), so it arrives after them.

A later layer (per-link / per-agent specs from CLI or config) only needs to produce `FaultRule`s.
"""

from __future__ import annotations

import hashlib
import heapq
import itertools
import logging
import random
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Annotated

import msgspec
from hammer.protocol.structs import Meta, Settings

Send = Callable[[bytes], None]
log = logging.getLogger(__name__)

_CHUNK_RE = re.compile(r"^(\*\*|\*|[A-Za-z0-9_.\-]+)$")


def validate_pattern(pattern: str) -> str:
    """A key pattern: '/'-separated chunks, each a name, `*` or `**` (raises ValueError)."""
    if not isinstance(pattern, str) or not pattern:
        raise ValueError("match pattern must be a non-empty string like 'agent/act/*' or '**'")
    for chunk in pattern.split("/"):
        if not _CHUNK_RE.match(chunk):
            raise ValueError(
                f"bad chunk {chunk!r} in match pattern {pattern!r}: each chunk is a name "
                "(letters, digits, _ . -), '*' (one chunk) or '**' (any number of chunks)"
            )
    return pattern


def key_matches(pattern: str, key: str) -> bool:
    """Zenoh-style match of a concrete key against a pattern with `*` and `**` chunks."""
    p, k = pattern.split("/"), key.split("/")

    def m(i: int, j: int) -> bool:
        if i == len(p):
            return j == len(k)
        if p[i] == "**":
            return any(m(i + 1, jj) for jj in range(j, len(k) + 1))
        if j == len(k):
            return False
        return (p[i] == "*" or p[i] == k[j]) and m(i + 1, j + 1)

    return m(0, 0)


Probability = Annotated[float, Meta(ge=0.0, le=1.0)]
Millis = Annotated[float, Meta(ge=0.0, le=60_000.0)]
Window = Annotated[int, Meta(ge=1, le=1000)]
HoldMillis = Annotated[float, Meta(gt=0.0, le=60_000.0)]


class FaultRule(Settings):
    """Faults for the keys matching `match` (relative to `hammer/<run>/`)."""

    match: str = "**"  # key pattern relative to hammer/<run>/, e.g. 'agent/act/*'
    drop: Probability = 0.0  # probability a message is lost
    duplicate: Probability = 0.0  # probability a message is sent twice
    delay_ms: Millis = 0.0  # mean extra latency in ms
    jitter_ms: Millis = 0.0  # latency varies uniformly by +-jitter_ms
    reorder: Probability = 0.0  # probability a message is held back
    reorder_window: Window = 1  # later messages that overtake a held one
    reorder_max_hold_ms: HoldMillis = 100.0  # a held message goes out after this

    def check(self) -> None:
        try:
            validate_pattern(self.match)
        except ValueError as e:
            raise ValueError(f"match: {e}") from None

    @property
    def label(self) -> str:
        return self.match


class FaultSpec(Settings):
    """A seed and an ordered list of rules (first match wins). No rules = no faults."""

    seed: int = 0
    rules: list[FaultRule] = msgspec.field(default_factory=list)

    @property
    def enabled(self) -> bool:
        return any(
            r.drop or r.duplicate or r.delay_ms or r.jitter_ms or r.reorder for r in self.rules
        )


@dataclass
class FaultCounters:
    """What one rule did. `sent` counts copies actually handed to Zenoh (duplicates count twice)."""

    matched: int = 0
    sent: int = 0
    dropped: int = 0
    duplicated: int = 0
    delayed: int = 0
    reordered: int = 0

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


@dataclass
class _Held:
    payload: bytes
    copies: int
    delay_s: float
    send: Send
    countdown: int
    released: bool = False


@dataclass
class _Stream:
    """Per (rule, key) state: its RNG and the messages it holds back."""

    rule_index: int
    rng: random.Random
    held: list[_Held] = field(default_factory=list)


def _stream_seed(seed: int, rule_index: int, key: str) -> int:
    digest = hashlib.blake2b(f"{seed}/{rule_index}/{key}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little")


class FaultInjector:
    """Applies a FaultSpec to outgoing payloads; delayed sends run on one scheduler thread."""

    def __init__(self, spec: FaultSpec) -> None:
        self.spec = spec
        self.counters = [FaultCounters() for _ in spec.rules]
        self._streams: dict[str, _Stream | None] = {}
        self._lock = threading.Condition()
        self._heap: list[tuple[float, int, Callable[[], None]]] = []
        self._tie = itertools.count()
        self._thread: threading.Thread | None = None
        self._closed = False

    # ---- public ---------------------------------------------------------------------------

    def submit(self, key: str, payload: bytes, send: Send) -> None:
        """Send `payload` with `send` (now, later, twice or never) per the rule matching `key`."""
        stream = self._stream(key)
        if stream is None:
            send(payload)
            return
        now_actions: list[Callable[[], None]] = []
        with self._lock:
            rule = self.spec.rules[stream.rule_index]
            c = self.counters[stream.rule_index]
            c.matched += 1
            # Always draw the same four numbers so the stream depends only on the message count.
            u_drop, u_dup, u_reorder, u_jitter = (stream.rng.random() for _ in range(4))
            if u_drop < rule.drop:
                c.dropped += 1
                return
            copies = 2 if u_dup < rule.duplicate else 1
            if copies == 2:
                c.duplicated += 1
            delay_ms = max(0.0, rule.delay_ms + rule.jitter_ms * (2.0 * u_jitter - 1.0))
            if u_reorder < rule.reorder:
                c.reordered += 1
                held = _Held(payload, copies, delay_ms / 1e3, send, rule.reorder_window)
                stream.held.append(held)
                self._schedule(rule.reorder_max_hold_ms / 1e3, lambda: self._release(stream, held))
                return
            now_actions += self._emit(stream.rule_index, payload, copies, delay_ms / 1e3, send)
            for held in list(stream.held):
                held.countdown -= 1
                if held.countdown <= 0:
                    now_actions += self._release_locked(stream, held)
        for action in now_actions:
            action()

    def pending(self) -> int:
        """Scheduled sends not yet done (delayed copies and held messages' release timers)."""
        with self._lock:
            return len(self._heap)

    def wait_idle(self, timeout: float = 10.0) -> bool:
        """Wait until every delayed or held message went out; False on timeout."""
        deadline = time.monotonic() + timeout
        while self.pending():
            if time.monotonic() > deadline:
                return False
            time.sleep(0.005)
        return True

    def flush(self) -> None:
        """Send everything held or delayed right now, in due order (used at close)."""
        with self._lock:
            pending = sorted(self._heap)
            self._heap.clear()
        for _, _, action in pending:
            action()

    def close(self) -> None:
        """Flush pending messages and stop the scheduler thread."""
        with self._lock:
            self._closed = True
            self._lock.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self.flush()

    def report(self) -> dict[str, dict[str, int]]:
        """Counters per rule, keyed by 'index:match'."""
        with self._lock:
            return {f"{i}:{r.match}": self.counters[i].as_dict() for i, r in enumerate(self.spec.rules)}

    # ---- internals ------------------------------------------------------------------------

    def _stream(self, key: str) -> _Stream | None:
        if key in self._streams:
            return self._streams[key]
        stream = None
        for i, rule in enumerate(self.spec.rules):
            if key_matches(rule.match, key):
                stream = _Stream(i, random.Random(_stream_seed(self.spec.seed, i, key)))
                break
        with self._lock:
            return self._streams.setdefault(key, stream)

    def _sender(self, rule_index: int, payload: bytes, send: Send) -> Callable[[], None]:
        def go() -> None:
            with self._lock:
                self.counters[rule_index].sent += 1
            send(payload)

        return go

    def _emit(self, rule_index: int, payload: bytes, copies: int, delay_s: float, send: Send) -> list:
        """Actions to run now (caller runs them outside the lock); delayed copies are scheduled."""
        actions = [self._sender(rule_index, payload, send) for _ in range(copies)]
        if delay_s <= 0.0:
            return actions
        self.counters[rule_index].delayed += 1
        for a in actions:
            self._schedule(delay_s, a)
        return []

    def _release_locked(self, stream: _Stream, held: _Held) -> list:
        if held.released:
            return []
        held.released = True
        stream.held.remove(held)
        return self._emit(stream.rule_index, held.payload, held.copies, held.delay_s, held.send)

    def _release(self, stream: _Stream, held: _Held) -> None:
        with self._lock:
            actions = self._release_locked(stream, held)
        for a in actions:
            a()

    def _schedule(self, delay_s: float, action: Callable[[], None]) -> None:
        """Run `action` after delay_s on the scheduler thread (caller holds the lock)."""
        heapq.heappush(self._heap, (time.monotonic() + delay_s, next(self._tie), action))
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="hammer-faults", daemon=True)
            self._thread.start()
        self._lock.notify_all()

    def _run(self) -> None:
        while True:
            with self._lock:
                while not self._closed and (not self._heap or self._heap[0][0] > time.monotonic()):
                    timeout = self._heap[0][0] - time.monotonic() if self._heap else None
                    self._lock.wait(timeout)
                if self._closed:
                    return
                now = time.monotonic()
                due = []
                while self._heap and self._heap[0][0] <= now:
                    due.append(heapq.heappop(self._heap)[2])
            for action in due:
                try:
                    action()
                except Exception as e:  # noqa: BLE001 - a closed publisher at shutdown must not kill the scheduler
                    log.warning("delayed send failed: %s", e)
