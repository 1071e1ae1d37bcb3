"""The thread every hostile test peer runs in (tests/hostile_peer.py, tests/stall_peer.py)."""

from __future__ import annotations

import threading


class PeerThread(threading.Thread):
    """Runs `_attack` until `stop_event` is set; an exception is kept in `error` for the test to
    report (a peer's failure must fail the test, not vanish in a daemon thread)."""

    def __init__(self, name: str) -> None:
        super().__init__(daemon=True, name=name)
        self.stop_event = threading.Event()
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            self._attack()
        except BaseException as e:  # noqa: BLE001 - the test reports it
            self.error = e

    def _attack(self) -> None:
        raise NotImplementedError
