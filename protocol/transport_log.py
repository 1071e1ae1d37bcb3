"""Connections Zenoh refused, counted: so an attack on a fleet's port does not read as a link failure.

Zenoh refuses a stranger at the TLS handshake (no certificate of the run's CA, a revoked robot's
certificate, plain TCP on a TLS port) inside its Rust transport, where no Python code sees it: the
only trace is a line of its own log (target `zenoh_link_tls::unicast`, level WARN), which
zenoh-python writes to the process's stdout once `zenoh.init_log_from_env_or` is called. So a process
that wants the count (a fleet's launcher, world and central agent) calls `watch_refused()` before it
opens a session: Zenoh then logs that target only (and ERRORs), and stdout (fd 1) becomes a pipe
that a thread reads line by line: a refusal is counted by reason and logged once in plain words
(the first 10, then every 1000th); every other line goes on to the real stdout unchanged.
`refused_counts()` is what a role's heartbeat reports (`refused.<reason>`, runtime/role.py).

Reasons: `tls_certificate` (a certificate that chains to nothing this process trusts: another CA's,
or a revoked robot's), `tls_plain` (not TLS at all: plain Zenoh or any other bytes), `tls_alert` (the
other side gave up on the handshake: it does not trust this process's certificate), `tls_other`.
"""

from __future__ import annotations

import collections
import logging
import os
import re
import threading

log = logging.getLogger("hammer.transport")

ZENOH_FILTER = "error,zenoh_link_tls::unicast=warn"
_ANSI = re.compile(rb"\x1b\[[0-9;]*m")
_REFUSAL = re.compile(rb"zenoh_link_tls::unicast: (.*?)(?:\. Hint:.*)?$")

_counts: collections.Counter[str] = collections.Counter()
_lock = threading.Lock()
_started = False


def reason_of(message: str) -> str:
    if "invalid peer certificate" in message or "certificate" in message.lower():
        return "tls_certificate"
    if "InvalidContentType" in message or "corrupt message" in message:
        return "tls_plain"
    if "received fatal alert" in message:
        return "tls_alert"
    return "tls_other"


def note_line(line: bytes) -> bool:
    """Count `line` if it is one of Zenoh's refusals (True), else False (the caller passes it on)."""
    m = _REFUSAL.search(_ANSI.sub(b"", line).rstrip(b"\r\n"))
    if m is None:
        return False
    message = m.group(1).decode("utf-8", "replace")
    reason = reason_of(message)
    with _lock:
        _counts[reason] += 1
        n = _counts[reason]
    if n <= 10 or n % 1000 == 0:
        log.warning("refused a connection #%d (%s): %s", n, reason, message)
    return True


def refused_counts() -> dict[str, int]:
    with _lock:
        return dict(_counts)


def watch_refused() -> bool:
    """Count the connections Zenoh refuses in this process (once per process; before any session).
    False when Zenoh's log is already set up by the user (RUST_LOG): it then goes where they said."""
    global _started
    if _started:
        return True
    if os.environ.get("RUST_LOG"):
        return False
    import zenoh

    read_end, write_end = os.pipe()
    real_stdout = os.dup(1)
    os.dup2(write_end, 1)
    os.close(write_end)

    def pump() -> None:
        with os.fdopen(read_end, "rb", buffering=0) as r, os.fdopen(real_stdout, "wb", buffering=0) as out:
            pending = b""
            while chunk := r.read(65536):
                pending += chunk
                *lines, pending = pending.split(b"\n")
                for line in lines:
                    if not note_line(line):
                        out.write(line + b"\n")
            if pending:
                out.write(pending)

    thread = threading.Thread(target=pump, name="zenoh-log", daemon=True)
    thread.start()
    restore = os.dup(real_stdout)

    def finish() -> None:  # at exit: what is still in the pipe reaches the real stdout
        import sys

        sys.stdout.flush()
        os.dup2(restore, 1)  # the pipe's last writer gone: the pump reads to the end and stops
        thread.join(2.0)

    import atexit

    atexit.register(finish)
    zenoh.init_log_from_env_or(ZENOH_FILTER)
    _started = True
    return True
