"""Which policy version an acting role uses, when weights arrive ahead of the step that needs them.

Every observation / global state carries the policy version its rollout runs on. In the
synchronous runtime that is always the newest version. With a policy lag (RuntimeSettings
`max_policy_lag` > 0) the learner publishes version v+1 while the env host is still collecting a
rollout on version v; an actor that switched at once would mix two versions in one rollout, and
the learner could no longer say which policy produced the experience. So received weights are
held, and loaded only when a step asks for their version (or a newer one): each rollout is acted
by exactly one version.

Torch-free: the edge local-agent client uses this.
"""

from __future__ import annotations

from collections.abc import Callable


class WeightsInbox:
    """Holds received weight blobs by version; `select(need)` loads the newest held version <= need."""

    def __init__(self, load: Callable[[bytes, int], None], version: int = -1, keep: int = 4) -> None:
        self._load = load
        self.version = version
        self.keep = keep
        self.held: dict[int, bytes] = {}
        self.loaded = 0

    def offer(self, version: int, blob: bytes) -> None:
        """Keep a received version (older than the loaded one or already held: ignored)."""
        if version <= self.version or version in self.held:
            return
        self.held[version] = blob
        for v in sorted(self.held)[: max(0, len(self.held) - self.keep)]:
            del self.held[v]

    def select(self, need: int | None = None) -> bool:
        """Load the newest held version <= `need` (None: the newest held); True if one was loaded."""
        usable = [v for v in self.held if need is None or v <= need]
        if not usable:
            return False
        v = max(usable)
        self._load(self.held[v], v)
        self.version = v
        self.loaded += 1
        for old in [u for u in self.held if u <= v]:
            del self.held[old]
        return True
