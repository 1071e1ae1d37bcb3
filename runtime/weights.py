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
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from hammer.learning.policy_versions import WeightsInbox
from hammer.protocol.schemas import Weights
from hammer.protocol.session import HammerSession
from hammer.runtime.bounds import DEFAULT_RESYNC_S, FIRST_VERSION_SLACK, StepWindow, version_ahead

log = logging.getLogger("hammer.weights")
FETCH_EVERY_S = 1.0  # a role without the version it needs asks again this often


class WeightsIntake:
    """The subscription to one network's weights (`local` or `central`) and the versions held."""

    def __init__(self, session: HammerSession, network: str, load: Callable[[bytes, int], None],
                 timeout_s: float, version: int = -1, *, reject: Callable[[str, str], None] | None = None,
                 max_policy_lag: int = 0, start_version: int | None = None,
                 resync_s: float | None = DEFAULT_RESYNC_S) -> None:
        """start_version: the version the run is known to be at (runtime.bounds.known_version); None:
        unknown (an edge agent from a bundle), the first weights received set the reference."""
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
        self._inbox.offer(w.version, w.blob)
