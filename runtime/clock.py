"""A fixed-rate clock for the roles of a fleet (the realtime world, the fleet-fed central agent).

Why its own: a fleet's loop runs on time, not on input. A tick that comes late is served at once
and the ticks it overran are skipped, never caught up in a burst: a world that fell 200 ms behind
must not step the physics ten times in a row, and a central agent must not send ten messages at
once. The overruns are counted, so a slow host shows as a number, not as a silently slower world.
"""

from __future__ import annotations

import time

# A simulated fleet's tick: its observations wait this long (at most) for the central agent's messages
# of the tick, which they carry (env_host/world.py; `--runtime msg_wait_s=S` on `hammer serve --realtime`).
MSG_WAIT_S = 0.01
# A fleet's central agent holds the site feed (what no robot observes) this long after its latest state
# arrived, then puts zeros in its columns (central_agent/fleet_central.py; `--runtime site_hold_s=S`).
SITE_HOLD_S = 1.0


class Clock:
    """Ticks at `hz`; `due(timeout)` sleeps until the next tick (at most `timeout` s)."""

    def __init__(self, hz: float) -> None:
        if not hz > 0:
            raise ValueError(f"a clock needs a rate > 0 Hz, got {hz}")
        self.period = 1.0 / hz
        self.next = time.monotonic()
        self.ticks = 0
        self.skipped = 0  # ticks overrun and not served

    def due(self, timeout: float) -> bool:
        """True when a tick is due (then the next one is scheduled); else False after `timeout` s."""
        now = time.monotonic()
        wait = self.next - now
        if wait > 0:
            if wait > timeout:
                time.sleep(timeout)
                return False
            time.sleep(wait)
            now = time.monotonic()
        late = int((now - self.next) // self.period)
        self.skipped += late
        self.next += (late + 1) * self.period
        self.ticks += 1
        return True
