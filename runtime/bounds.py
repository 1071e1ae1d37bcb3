"""What a role accepts from the wire, bounded: a step window and a weights-version bound.

Validation (protocol.codec) checks that a message is well formed; it cannot know that a step
number of 2^63 is absurd. One such message, adopted, froze a role for the rest of a run: every
later (real) step looked stale. So a role adopts a step only inside a window around the last
step it acted on, and a policy version only within what the protocol allows (the learner is the
only publisher; versions advance by one per update, actors may lag by max_policy_lag):

    step s      accepted when last < s <= last + W        (W: RuntimeSettings.step_window)
    version v   accepted when v <= newest known + 1 + L   (L: max_policy_lag)

Before a role has acted on any step (or held any version) there is nothing to measure against:
the first one anchors the window (a restarted role joins a run already under way).

A window that the real stream itself leaves (a role paused for longer than W steps) would stall
the role for good, so a role that has accepted nothing inside its window for `resync_s` while
out-of-window steps keep coming, each following the one before it (inside a window of the previous
rejected step), adopts the newest: one forged message cannot do that, a role that is already getting
nothing else but a steady stream can.
"""

from __future__ import annotations

import time

DEFAULT_STEP_WINDOW = 10_000
DEFAULT_RESYNC_S = 5.0


def version_ahead(version: int, known: int, max_policy_lag: int) -> bool:
    """A weights version further ahead than the learner can be (known < 0: nothing held yet)."""
    return known >= 0 and version > known + 1 + max_policy_lag


class StepWindow:
    """The step window of one input of a role (see the module docstring)."""

    def __init__(self, width: int = DEFAULT_STEP_WINDOW, resync_s: float | None = DEFAULT_RESYNC_S) -> None:
        self.width, self.resync_s = width, resync_s
        self._in_window_t = time.monotonic()
        self._rejected = -1  # the last step rejected as ahead: a stream re-anchors only if it continues it

    def ahead(self, step: int, last: int) -> bool:
        """True: `step` lies beyond the window after `last` and must be rejected (counted by the caller)."""
        now = time.monotonic()
        if last < 0 or step <= last + self.width:
            self._in_window_t = now
            return False
        follows = self._rejected >= 0 and self._rejected < step <= self._rejected + self.width
        self._rejected = step
        if follows and self.resync_s is not None and now - self._in_window_t > self.resync_s:
            self._in_window_t = now  # nothing else came for resync_s, and the stream moves on steadily
            return False
        return True
