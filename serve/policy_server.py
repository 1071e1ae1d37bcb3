"""Serving a trained team: its exported policy, published as the learner would; never learns.

Deployment and evaluation run the real runtime (every hop, every fault) but must not change the
policy, so this server (role `policy`) takes the learner's place: it publishes the exported
`local.safetensors` (and `central.safetensors` for HAMMER) as policy version 0, once per version,
and answers queries for the current one (`HammerSession.answer`): a role that joins late, or
missed a version, asks (runtime/weights.py) and the copy crosses its own link only. Why: the
weights are 35-39 kB; republished to every agent whenever one joined, they held a 256 kbit/s link
for 1.2 s each time (docs/deploy.md, "Real links"). A periodic republish with a back-off
(`republish_s`, doubling up to `republish_max_s`) is there for runs that want one; off by default.
The files are sent as they are (safetensors, never pickle); numpy and zenoh only, so serving does
not pay for a torch import.

Given the run directory, it also follows the run's update history (serve/push.py: `hammer push`,
`hammer rollback`, and a staged rollout, serve/canary.py): the newest entry's weights, checked
against their recorded sha256, become the published version (the env host names it from the next
step on, for every agent or, during a canary, for the canary's agents). An entry that names the
version already published (a stage, a promotion, a gate record) publishes nothing. During a canary
two versions are in use, so a query is answered with both (the base and the canary): a role that
(re)joins mid-canary then holds the one its steps name, instead of the newest only, which would put
an agent outside the canary on the canary's policy (runtime/weights.py loads the version a step
names, or the newest below it).

A pushed version of the local policy is not published whole when `chunk_bytes` > 0 (RuntimeSettings
`weights_chunk_bytes`, the default): it is announced (WeightsAnnounce: size, sha256, each chunk's
digest; repeated 4, 12 and 28 s after the first (waits of 4, 8 and 16 s) for who missed it: not sooner, since each copy crosses every
thin link while the agents step, and an agent that missed it still gets the version, whole, when
the env host names it after `weights_name_timeout_s`) and every local agent pulls its
chunks by query (`learn/local/chunk?v=<version>&i=<index>`, `_answer_chunk`), one at a time, after
its step's action (runtime/weights.py), so a push never puts more than one chunk ahead of a thin
link's step traffic. The central agent's link is on the server side: it gets the whole weights.
Version 0 and a late joiner's query are answered whole.
"""

from __future__ import annotations

import time
from pathlib import Path

from hammer.protocol.access import POLICY
from hammer.protocol.schemas import Weights, WeightsAnnounce, WeightsChunk
from hammer.protocol.session import HammerSession
from hammer.runtime.role import Role
from hammer.runtime.settings import RuntimeSettings

ANNOUNCE_FIRST_S, ANNOUNCE_LAST_S = 4.0, 16.0  # waits of 4, 8 and 16 s between an announcement's copies (docstring)


class PolicyDirError(FileNotFoundError):
    """The policy directory lacks a file the run needs."""


def policy_blobs(policy_dir: Path, needs_central: bool) -> dict[str, bytes]:
    """role -> safetensors bytes from an exported policy directory (RUN/final)."""
    policy_dir = Path(policy_dir)
    files = {"local": policy_dir / "local.safetensors"}
    if needs_central:
        files["central"] = policy_dir / "central.safetensors"
    for role, f in files.items():
        if not f.is_file():
            raise PolicyDirError(f"{f} is missing: policy_dir must hold the {role} policy a run exports "
                                 "(RUN/final/ after `hammer train` or `hammer up`)")
    return {role: f.read_bytes() for role, f in files.items()}


class PolicyServer(Role):
    """Publishes the frozen weights (version 0, then each pushed version) until a stop command, and
    answers whoever asks for the current version; the settings' `weights_republish_s` > 0: also
    republishes with a back-off (doubling up to `weights_republish_max_s`); `weights_float16`,
    `weights_chunk_bytes`: what goes on the wire."""

    def __init__(self, session: HammerSession, policy_dir: Path, needs_central: bool, settings: RuntimeSettings,
                 run_dir: Path | None = None) -> None:
        self.float16, self.chunk_bytes = settings.weights_float16, settings.weights_chunk_bytes
        republish_s, republish_max_s = settings.weights_republish_s, settings.weights_republish_max_s
        chunk_bytes = self.chunk_bytes
        blobs = self._wire(policy_blobs(policy_dir, needs_central))  # a missing file fails before anything is declared
        super().__init__(session, POLICY, report_faults=False, stall_warn_s=settings.stall_warn_s)
        self.blobs, self.needs_central = blobs, needs_central
        self.republish_s = republish_s
        self.republish_max_s = max(republish_s, republish_max_s)
        self.period = republish_s  # the wait before the next republish: doubles up to republish_max_s
        self.pubs = {role: session.publisher(self.keys.weights(role)) for role in blobs}
        self.published = self.answered = 0
        self.last_publish = 0.0
        self.version, self.run_dir, self.history_seen = 0, run_dir, 0
        self.updates_rejected = 0
        self._current: dict[str, Weights] = {}
        self._also: dict[str, Weights] = {}  # during a canary: the base version, answered with the current one
        self.policy_dir = Path(policy_dir)
        self._by_version: dict[int, dict[str, bytes]] = {0: blobs}  # wire blobs published, for the canary's base
        for role in blobs:
            session.answer(self.keys.weights(role), lambda role=role: self._answer(role))
        self.announces = self.chunks_answered = 0
        self._announce: WeightsAnnounce | None = None  # the pushed local version, pulled in chunks
        self._announce_at, self._announce_wait = 0.0, ANNOUNCE_FIRST_S
        self._chunked: dict[int, bytes] = {}  # version -> the local blob its chunks are cut from (the last few)
        if chunk_bytes > 0:
            self.announce_pub = session.publisher(self.keys.weights_announce("local"))
            session.answer(self.keys.weights_chunk("local"), self._answer_chunk, parameters=True)

    def _wire(self, blobs: dict[str, bytes]) -> dict[str, bytes]:
        """The blobs as sent: float16 tensors with `float16` (learning.numpy_policy.float16_blob)."""
        if not self.float16:
            return blobs
        from hammer.learning.numpy_policy import float16_blob

        return {role: float16_blob(b) for role, b in blobs.items()}

    def _answer(self, role: str) -> list[Weights]:
        """The current version's weights for a query, and the base version's during a canary (on a
        Zenoh thread: only hands over what it has)."""
        out = [w for w in (self._also.get(role), self._current.get(role)) if w is not None]
        self.answered += bool(out)
        return out

    def _answer_chunk(self, params: dict[str, str]) -> WeightsChunk | None:
        """Chunk `i` of version `v` for the agent that asked (on a Zenoh thread; the parameters are
        untrusted: anything but two small decimal numbers naming a chunk held gets no reply)."""
        v, i = params.get("v", ""), params.get("i", "")
        if not (v.isdecimal() and i.isdecimal() and len(v) <= 18 and len(i) <= 6):
            return None
        blob, n = self._chunked.get(int(v)), self.chunk_bytes
        if blob is None or int(i) * n >= len(blob):
            return None
        self.chunks_answered += 1
        return WeightsChunk(role="local", version=int(v), index=int(i), data=blob[int(i) * n:(int(i) + 1) * n])

    def counters(self) -> dict[str, int]:
        return {"frozen_publishes": self.published, "updates_rejected": self.updates_rejected,
                "weights_answered": self.answered, "weights_announced": self.announces,
                "chunks_answered": self.chunks_answered}

    def gauges(self) -> dict[str, int]:
        return {"policy_version": self.version}

    def on_start(self) -> None:
        self.publish()

    def poll(self, timeout: float) -> bool:
        """Nothing to receive: queries are answered on Zenoh's thread (`_answer`)."""
        time.sleep(timeout)
        return False

    def on_idle(self) -> None:
        if self.run_dir is not None:
            self.follow_history()
        if self.republish_s > 0 and time.monotonic() - self.last_publish >= self.period:
            self.publish()
            self.period = min(self.period * 2, self.republish_max_s)
        if (self._announce is not None and self._announce_wait <= ANNOUNCE_LAST_S
                and time.monotonic() - self._announce_at >= self._announce_wait):
            self._announce_at, self._announce_wait = time.monotonic(), self._announce_wait * 2
            self.announce_pub.publish(self._announce)  # for an agent that missed it (a few hundred bytes)
            self.announces += 1

    def follow_history(self) -> None:
        """New entries in RUN/pushes.json: publish each new version (`_publish_entry`); a stage, a
        promotion or a gate record names the version already published and publishes nothing."""
        from hammer.runtime.pushes import assignment
        from hammer.serve.bundle import BundleError
        from hammer.serve.push import read_history

        try:
            entries = read_history(self.run_dir)
        except BundleError as e:
            if self.history_seen >= 0:
                self.log.error("%s", e)
            self.history_seen = -1
            return
        if len(entries) <= max(self.history_seen, 0):
            return
        new, self.history_seen = entries[max(self.history_seen, 0):], len(entries)
        # Every new version in order, not only the newest: a role rejects weights more than one
        # version ahead of what it holds (runtime.bounds), so a push and its quick rollback (a canary
        # interrupted at once) seen in one read must not skip the push's version.
        for i, e in enumerate(new):
            if e["version"] > self.version and all(e["version"] != later["version"] for later in new[i + 1:]):
                self._publish_entry(e)
        self._keep_base(assignment(entries))

    def _publish_entry(self, e: dict) -> None:
        """Load an entry's weights (hash-checked) and publish them as its version."""
        from hammer.serve.bundle import sha256

        try:
            blobs = policy_blobs(Path(e["policy_dir"]), self.needs_central)
            bad = [n for n, d in e.get("files", {}).items() if sha256(Path(e["policy_dir"]) / n) != d]
            if bad:
                raise PolicyDirError(f"{', '.join(bad)}: sha256 differs from pushes.json")
        except PolicyDirError as err:
            self.updates_rejected += 1
            self.log.error("update to version %d rejected: %s", e["version"], err)
            return
        self.blobs, self.version = self._wire(blobs), e["version"]
        if self.chunk_bytes > 0:
            self._chunked = {**{v: b for v, b in self._chunked.items() if v >= self.version - 4},
                             self.version: self.blobs["local"]}
            self._announce = WeightsAnnounce.of("local", self.version, self.blobs["local"], self.chunk_bytes)
            self._announce_at, self._announce_wait = time.monotonic(), ANNOUNCE_FIRST_S
        self._by_version = {**{v: b for v, b in self._by_version.items() if v >= self.version - 8},
                            self.version: self.blobs}
        self.log.info("%s: publishing version %d from %s", e.get("action", "push"), self.version, e["policy_dir"])
        self.period = self.republish_s  # a new version: republished soon for anyone who missed the first copy
        self.publish()
        self.heartbeat_soon()

    def _keep_base(self, a) -> None:
        """Answer queries with the base version too while a canary of the current version is open."""
        if a.canary != self.version or a.base == self.version:
            self._also = {}
            return
        blobs = self._by_version.get(a.base)
        if blobs is None:  # started mid-canary: the base's files (checked when it was pushed)
            try:
                blobs = self._wire(policy_blobs(Path(a.dirs.get(a.base, self.policy_dir)), self.needs_central))
            except PolicyDirError as err:
                self.log.error("base version %d of the canary not answerable: %s", a.base, err)
                return
        self._also = {role: Weights.from_blob(role, a.base, blob) for role, blob in blobs.items()}

    def publish(self) -> None:
        self._current = {role: Weights.from_blob(role, self.version, blob) for role, blob in self.blobs.items()}
        for role, w in self._current.items():
            if role == "local" and self._announce is not None and self._announce.version == self.version:
                self.announce_pub.publish(self._announce)  # the agents pull it in chunks
                self.announces += 1
            else:
                self.pubs[role].publish(w)
        self.published += 1
        self.last_publish = time.monotonic()

    def on_stop(self) -> None:
        self.log.info("stopped after %d publishes", self.published)
