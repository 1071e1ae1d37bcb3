"""Weights intake of an acting role: hold what the learner publishes, load what a step asks for.

The central agent and every local agent act with the policy version their step names (the
observation / global state carries it). Weights can arrive before that step (policy lag) or a
little after the step that needs them (the learner publishes as the env host moves on), so an
acting role holds received versions (`learning.policy_versions.WeightsInbox`) and, when a step
names a version it has not loaded, waits for it up to a timeout, then acts with what it has and
counts the timeout. A role that holds no policy, or waits for a version, asks for it (a query the
policy server of a served run answers, `HammerSession.fetch`, at most once every `FETCH_EVERY_S`):
a late joiner gets the policy over its own link instead of everyone getting a republish. A
reply is validated and bounded as a publication is. A version further ahead than the learner can be (runtime.bounds) is
rejected, never held: one forged `Weights` of version 2^62 must not become "the newest", neither
before the first real weights (the run's known version is the reference then) nor after.
Torch-free: the edge local agent uses it.

A pushed version of the local policy comes as an announcement (WeightsAnnounce: size, sha256,
each chunk's digest) that the agent pulls itself, one chunk per query, one query outstanding
(`pump`, called once per step and on the idle timer): on a thin link at most one small chunk then
waits in the kernel's queue ahead of a step's traffic, instead of the whole weights (docs/deploy.md,
"A push on a thin link"). When in the step: once the step's observation and message are in,
before the action goes out. The link down to the agent carries nothing more of this step then,
and the next observation only leaves the env host after this action went up, so the chunk crosses
while the link is idle; asked after the action, the chunk met the next observation and message in
the queue and one step in three acted on a late message (measured at 256 kbit/s). A chunk whose size or digest disagrees with the
announcement is refused and counted (`chunks_refused`) and asked again; the reassembled blob is
checked against the announced sha256 before it is held. Bytes already held under the announced
sha256 (a rollback to weights the agent had) are taken without a pull. The heartbeat's
`policy_held` gauge (`known`) tells the env host which version an agent holds: it names a pushed
version only once the agents it is for hold it (env_host/host.py).
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Callable

from hammer.learning.policy_versions import WeightsInbox
from hammer.protocol.schemas import Weights, WeightsAnnounce, WeightsChunk, chunk_digest
from hammer.protocol.session import HammerSession
from hammer.runtime.bounds import DEFAULT_RESYNC_S, FIRST_VERSION_SLACK, StepWindow, version_ahead

log = logging.getLogger("hammer.weights")
FETCH_EVERY_S = 1.0  # a role without the version it needs asks again this often
CHUNK_RETRY_S = 2.0  # a chunk asked for and not received in this long is asked again
IDLE_PULL_EVERY_S = 0.2  # while no steps come, a pull asks for its next chunk at most this often
KEEP_BLOBS = 4  # blobs remembered by sha256 (a rollback to weights held before needs no pull)


class ChunkPull:
    """One announced version being put together from its chunks."""

    def __init__(self, announce: WeightsAnnounce) -> None:
        self.announce = announce
        self.parts: list[bytes | None] = [None] * announce.chunks
        self.asked: int | None = None  # the one chunk asked for and not received yet
        self.asked_at = 0.0
        self.started = time.monotonic()

    @property
    def version(self) -> int:
        return self.announce.version

    def missing(self) -> int | None:
        """The first chunk not received (None: complete)."""
        return next((i for i, p in enumerate(self.parts) if p is None), None)

    def refusal(self, c: WeightsChunk) -> str | None:
        """Why chunk `c` of this version cannot be taken (None: it can)."""
        a = self.announce
        if c.index >= a.chunks:
            return f"index {c.index} beyond the announced {a.chunks} chunks"
        if len(c.data) != a.chunk_size(c.index):
            return f"{len(c.data)} B, the announcement says {a.chunk_size(c.index)}"
        if chunk_digest(c.data) != a.digest(c.index):
            return "digest differs from the announcement"
        return None


class WeightsIntake:
    """The subscription to one network's weights (`local` or `central`) and the versions held."""

    def __init__(self, session: HammerSession, network: str, load: Callable[[bytes, int], None],
                 timeout_s: float, version: int = -1, *, reject: Callable[[str, str], None] | None = None,
                 max_policy_lag: int = 0, start_version: int | None = None,
                 resync_s: float | None = DEFAULT_RESYNC_S, on_held: Callable[[int], None] | None = None) -> None:
        """start_version: the version the run is known to be at (runtime.bounds.known_version); None:
        unknown (an edge agent from a bundle), the first weights received set the reference.
        on_held: called with a pulled version once it is held (the agent says so in a heartbeat)."""
        self.network = network
        # The reference before any weights: the known version + the slack a restart needs (runtime.bounds).
        self.first_reference = None if start_version is None else start_version + FIRST_VERSION_SLACK
        # Versions advance one per update: the bound is the step window's logic with width 1 + lag.
        self._bound = StepWindow(1 + max_policy_lag, resync_s=resync_s, start=self.first_reference, repeats=True)
        self.timeout_s = timeout_s
        self.max_policy_lag = max_policy_lag
        self._reject = reject or (lambda reason, what: log.warning("rejected (%s): %s", reason, what))
        self._session, self._key = session, session.keys.weights(network)
        self._sub = session.subscribe(self._key, Weights)
        self._inbox = WeightsInbox(load, version)
        self.fetches = 0  # queries sent for the current policy
        self._last_fetch = -FETCH_EVERY_S
        self.loaded = 0  # versions loaded
        self.wait_timeouts = 0  # steps that named a version which did not come in time
        self.versions_passed = 0  # a (re)started role's first version was gone: it took the next one
        # A push's chunks (the local policy only: the central agent's link is the server's).
        self._on_held = on_held or (lambda version: None)
        self._announces = self._chunks = None
        if network == "local":
            self._announces = session.subscribe(session.keys.weights_announce(network), WeightsAnnounce)
            self._chunks = session.subscribe(session.keys.weights_chunk(network), WeightsChunk, maxsize=16)
        self._chunk_key = session.keys.weights_chunk(network)
        self._pull: ChunkPull | None = None
        self._blobs: dict[str, bytes] = {}  # sha256 -> blob, the last KEEP_BLOBS received
        self._last_ask = 0.0
        self.chunk_queries = self.chunks_received = self.chunks_refused = 0
        self.versions_pulled = 0  # pushed versions put together from chunks and held
        self.pull_s = 0.0  # the last pull's duration: announcement received -> held

    @property
    def version(self) -> int:
        """The loaded version (-1: none yet)."""
        return self._inbox.version

    @property
    def known(self) -> int:
        """The newest version loaded or held (-1: none yet)."""
        return max(self._inbox.version, max(self._inbox.held, default=-1))

    @property
    def reference(self) -> int:
        """What the bound is measured from: the newest version held, else the run's (-1: none known)."""
        if self.known >= 0 or self.first_reference is None:
            return self.known
        return self.first_reference

    def ahead(self, need: int) -> bool:
        """A step naming version `need` names one the learner cannot have published yet."""
        return version_ahead(need, self.reference, self.max_policy_lag)

    def take(self, need: int | None) -> None:
        """Load the version `need` names, never a newer one (see WeightsInbox), waiting for it up to
        `timeout_s`; need=None: load the newest received, without waiting."""
        start = time.monotonic()
        deadline = start + self.timeout_s
        if need is None and self.known < 0:
            self.fetch()  # idle without a policy (the central agent of a served run): ask for the current one
        if need is not None and self.version < need and self._inbox.select(need):
            self.loaded += 1  # received during an earlier take (policy lag): held, not waited for
        while True:
            wait = 0.0 if need is None or self.version >= need else deadline - time.monotonic()
            if wait > 0 and need > self.known:  # not here: after a second's wait (a publication comes first), ask
                if time.monotonic() - start >= FETCH_EVERY_S:
                    self.fetch()
                wait = min(wait, FETCH_EVERY_S)
            w = self._sub.get(timeout=max(wait, 0.0))
            if w is not None:
                self._offer(w)
                if self._inbox.select(need):
                    self.loaded += 1
                elif need is not None and self.version < 0 and self._passed(need):
                    return
                continue
            if need is None or self.version >= need:
                return
            if time.monotonic() < deadline:
                continue
            self.wait_timeouts += 1
            log.warning("%s policy version %d not received in %.0fs; acting with %d",
                        self.network, need, self.timeout_s, self.version)
            return

    def receive(self) -> int:
        """Take what arrived without loading it; returns the newest version held and not loaded (-1: none)."""
        for w in self._sub.drain():
            self._offer(w)
        return max(self._inbox.held, default=-1)

    def take_newest(self) -> bool:
        """Take what arrived and load the newest version held, never waiting (True: one was loaded).
        For a role with no step to name a version (a fleet's robots and central agent,
        docs/fleet.md): each switches on its own as soon as it holds a newer version."""
        for w in self._sub.drain():
            self._offer(w)
        if self._inbox.select(None):
            self.loaded += 1
            return True
        return False

    def remember(self, blob: bytes) -> None:
        """Bytes this role already acts with (a robot's bundle): an announced version carrying them
        (a rollback to them) is then held at once, with no pull over the link."""
        self._remember(hashlib.sha256(blob).hexdigest(), blob)

    def _passed(self, need: int) -> bool:
        """A role holding no policy yet (just started or restarted) whose first steps name version
        `need` while only newer ones arrive: each version is published once (republished only to an
        idle run), so `need` will never come. Load the oldest newer one rather than wait out the
        timeout and act without a policy; counted (`versions_passed`) and logged."""
        newer = [v for v in self._inbox.held if v > need]
        if not newer or not self._inbox.select(min(newer)):
            return False
        self.loaded += 1
        self.versions_passed += 1
        log.warning("%s policy version %d is gone (the run is at %d): acting with %d from this step on",
                    self.network, need, max(newer), self.version)
        return True

    def preload_oldest(self) -> bool:
        """While idle with no policy: load the oldest version held, so the first step is not slowed
        by loading weights (a step never asks for a version older than the learner's first
        broadcast). True if one was loaded."""
        for w in self._sub.drain():
            self._offer(w)
        if self._inbox.held and self._inbox.select(min(self._inbox.held)):
            self.loaded += 1
            return True
        if self.known < 0:
            self.fetch()
        return False

    def fetch(self) -> None:
        """Ask for the current version (at most once every FETCH_EVERY_S); the reply, if anyone
        answers, arrives through the subscription."""
        now = time.monotonic()
        if now - self._last_fetch >= FETCH_EVERY_S:
            self._last_fetch = now
            self.fetches += 1
            self._session.fetch(self._key, self._sub)

    def _offer(self, w: Weights) -> None:
        if self._bound.ahead(w.version, self.known):
            self._reject("weights_ahead", f"{self.network} weights version {w.version} beyond {self.reference}")
            return
        self._remember(w.sha256, w.blob)
        self._inbox.offer(w.version, w.blob)

    def _remember(self, sha: str, blob: bytes) -> None:
        self._blobs[sha] = blob
        for old in list(self._blobs)[:max(0, len(self._blobs) - KEEP_BLOBS)]:
            del self._blobs[old]

    # ----- a push, pulled in chunks ---------------------------------------------------------------
    def pump(self, idle: bool = False) -> None:
        """Take announcements and chunk replies; ask for the next chunk of a pull in progress if none
        is outstanding. Called once per step, when the step's inputs are in and before its action
        goes out (the module docstring says why then), and, `idle`, on the idle timer (then at most
        every IDLE_PULL_EVERY_S)."""
        if self._announces is None:
            return
        for a in self._announces.drain():
            self._announced(a)
        for c in self._chunks.drain():
            self._chunk(c)
        p, now = self._pull, time.monotonic()
        if p is None or (p.asked is not None and now - p.asked_at < CHUNK_RETRY_S):
            return
        if idle and now - self._last_ask < IDLE_PULL_EVERY_S:
            return
        i = p.missing()
        if i is None:
            return
        p.asked, p.asked_at, self._last_ask = i, now, now
        self.chunk_queries += 1
        self._session.fetch(self._chunk_key, self._chunks, timeout=CHUNK_RETRY_S, parameters=f"v={p.version}&i={i}")

    @property
    def pulling(self) -> int | None:
        """The version being pulled (None: none)."""
        return None if self._pull is None else self._pull.version

    def _announced(self, a: WeightsAnnounce) -> None:
        if a.version <= self.known or (self._pull is not None and a.version <= self._pull.version):
            return  # held already, or being pulled (an announcement is repeated for who missed it)
        if self._bound.ahead(a.version, self.known):
            self._reject("weights_ahead", f"{self.network} announced version {a.version} beyond {self.reference}")
            return
        blob = self._blobs.get(a.sha256)
        if blob is not None and len(blob) == a.size:  # these bytes are here already (a rollback)
            self._pull = None
            self._hold(a.version, blob, a.sha256, 0.0)
            return
        if self._pull is not None:
            log.info("%s version %d announced: pulling it instead of %d", self.network, a.version, self._pull.version)
        self._pull = ChunkPull(a)

    def _chunk(self, c: WeightsChunk) -> None:
        p = self._pull
        if p is None or c.version != p.version:
            return  # a reply to an earlier pull, or a second reply to one already taken
        self.chunks_received += 1
        why = p.refusal(c)
        if why is None and p.parts[c.index] is None:
            p.parts[c.index] = c.data
        elif why is not None:
            self.chunks_refused += 1
            if self.chunks_refused <= 10 or self.chunks_refused % 1000 == 0:
                log.warning("%s version %d chunk %d refused (#%d): %s", self.network, c.version, c.index,
                            self.chunks_refused, why)
        if c.index == p.asked:
            p.asked = None  # answered (a refused chunk is asked again at the next pump)
        if p.missing() is not None:
            return
        blob, self._pull = b"".join(p.parts), None
        if hashlib.sha256(blob).hexdigest() != p.announce.sha256:  # only past 8-byte digests that all matched
            self.chunks_refused += 1
            log.warning("%s version %d: the chunks' sha256 differs from the announcement; pulling again",
                        self.network, p.version)
            self._pull = ChunkPull(p.announce)
            return
        self._hold(p.version, blob, p.announce.sha256, time.monotonic() - p.started)

    def _hold(self, version: int, blob: bytes, sha: str, took_s: float) -> None:
        self._remember(sha, blob)
        self._inbox.offer(version, blob)
        self.versions_pulled += 1
        self.pull_s = took_s
        log.info("%s version %d held (%d B, %.2f s after its announcement)", self.network, version, len(blob), took_s)
        self._on_held(version)

    def counters(self) -> dict[str, int | float]:
        """The pull's counters, for the agent's heartbeat."""
        return {"chunk_queries": self.chunk_queries, "chunks_received": self.chunks_received,
                "chunks_refused": self.chunks_refused, "versions_pulled": self.versions_pulled}
