"""What a role accepts from the wire, bounded: a step window and a weights-version bound.

Validation (protocol.codec) checks that a message is well formed; it cannot know that a step
number of 2^63 is absurd. One such message, adopted, froze a role for the rest of a run: every
later (real) step looked stale. So a role adopts a step only inside a window around the last
step it acted on, and a policy version only within what the protocol allows (the learner is the
only publisher; versions advance by one per update, actors may lag by max_policy_lag):

    step s      accepted when last < s <= last + W        (W: RuntimeSettings.step_window)
    version v   accepted when v <= newest known + 1 + L   (L: max_policy_lag)

Before a role has acted on any step, `last` is the step the run is known to be at (`known_step`):
the run's start (0, or the resume step) from runtime.json, or, for a role the launcher starts or
restarts, the env host's last reported step. So a forged step of 2^64-1 that arrives before a
role's first real one is rejected like any other, instead of anchoring the window. Only a role
with no known step at all (start=None: an edge agent joining from a bundle) adopts its first step.

Two streams can leave the window for real, and each is followed again only when it has been the
role's only input for `resync_s` and continues itself step after step (each step inside a window
of the one before it): one forged message can do neither.
- ahead: the real stream left the window upwards (a role paused for longer than W steps, or a
  role started with a known step far behind the run): the role adopts the stream's newest step;
- behind (`stale`): the role's anchor is above the real stream (a forged step inside the bound
  adopted before the first real one, or a hint from a forged heartbeat): at least
  `MIN_STREAM` in-order steps below the anchor and nothing accepted for resync_s, and the role
  drops its anchor and acts on the stream again.
Versions are bounded the same way: before a role holds any weights, the reference is the version
the run is known to be at (`known_version`: the resume update of runtime.json, or the env host's last
reported policy version, passed by the launcher to a role it starts) plus FIRST_VERSION_SLACK (the
learner moves on while a role restarts: that hint is a floor, not the version the role will see), so
a forged first `Weights` of version 2^62 is refused instead of disabling the bound for the rest of
the run; one inside the slack is held but loaded only if a step names it. A versions stream
beyond the bound is followed like a step stream ahead: when it has been the only weights for
`resync_s` and continues itself (a role that missed versions while paused, or started with a stale
hint). Only a role with no known version (an edge agent from a bundle) adopts its first one; the
secure profile's access rules let only the learner (or the policy server) publish weights at all.
"""

from __future__ import annotations

import os
import time

DEFAULT_STEP_WINDOW = 10_000
DEFAULT_RESYNC_S = 5.0
MIN_STREAM = 3  # in-order steps below the anchor before a role follows them (behind resync)
FIRST_VERSION_SLACK = 1_000  # updates the learner may make while a role (re)starts (>= 100 s at 10 a second)
RUN_STEP_ENV = "HAMMER_RUN_STEP"  # set by the launcher: the env host's last reported step
RUN_VERSION_ENV = "HAMMER_RUN_VERSION"  # set by the launcher: the env host's last reported policy version


def version_ahead(version: int, known: int, max_policy_lag: int) -> bool:
    """A weights version further ahead than the learner can be (known < 0: no reference yet)."""
    return known >= 0 and version > known + 1 + max_policy_lag


def known_version(resume_from: int | None) -> int:
    """The policy version a starting role's first weights cannot be far above: the run's start (0, or
    the resume update), or the env host's last reported policy version when the launcher passed it."""
    hint = os.environ.get(RUN_VERSION_ENV, "")
    return max(resume_from or 0, int(hint) if hint.isdigit() else 0)


def known_step(resume_step: int | None) -> int:
    """The step before the first one a starting role can see: the run's start (0, or the resume
    step of runtime.json), or the env host's last reported step when the launcher passed it
    (a role started or restarted mid-run; the real stream can only be ahead of it)."""
    hint = os.environ.get(RUN_STEP_ENV, "")
    return max(resume_step or 0, int(hint) if hint.isdigit() else 0)


class StepWindow:
    """The step window of one input of a role (see the module docstring). `start`: the step the
    run is known to be at before the role has acted on any (None: unknown, the first step anchors)."""

    def __init__(self, width: int = DEFAULT_STEP_WINDOW, resync_s: float | None = DEFAULT_RESYNC_S,
                 start: int | None = None, repeats: bool = False) -> None:
        """repeats=True: a stream ahead also continues by repeating its newest value (a policy server
        republishes its current version until everyone has it; steps never repeat)."""
        self.width, self.resync_s, self.start, self.repeats = width, resync_s, start, repeats
        self._in_window_t = time.monotonic()
        self._rejected = -1  # the last step rejected as ahead: a stream re-anchors only if it continues it
        self._behind, self._behind_run = -1, 0  # the last stale step and how many followed each other

    def ahead(self, step: int, last: int) -> bool:
        """True: `step` lies beyond the window after `last` and must be rejected (counted by the caller)."""
        now = time.monotonic()
        ref = last if last >= 0 else self.start
        if ref is None or step <= ref + self.width:
            self._in_window_t = now
            self._behind, self._behind_run = -1, 0
            return False
        low = self._rejected if self.repeats else self._rejected + 1
        follows = self._rejected >= 0 and low <= step <= self._rejected + self.width
        self._rejected = step
        return not (follows and self._resync_due(now))  # a stream that moves on steadily: followed

    def stale(self, step: int, last: int) -> bool:
        """`step` <= `last`: True, drop it as stale (the caller counts it); False, the stream below
        the anchor is the real one (MIN_STREAM in-order steps, nothing accepted for resync_s): the
        caller acts on it, which moves its anchor down."""
        follows = self._behind >= 0 and self._behind < step <= self._behind + self.width
        self._behind_run = self._behind_run + 1 if follows else 1
        self._behind = step
        if self._behind_run >= MIN_STREAM and self._resync_due(time.monotonic()):
            self._behind, self._behind_run = -1, 0
            return False
        return True

    def _resync_due(self, now: float) -> bool:
        if self.resync_s is None or now - self._in_window_t <= self.resync_s:
            return False
        self._in_window_t = now  # nothing else came for resync_s, and the stream moves on steadily
        return True
