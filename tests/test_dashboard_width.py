"""The live dashboard of `hammer up` in an 80-column terminal: a real run under a pseudo-terminal of
80 columns; every link name and count of the links table is shown whole (the table turns: a column
per link), and a wide terminal keeps a row per link."""

from __future__ import annotations

import fcntl
import os
import pty
import re
import select
import struct
import subprocess
import sys
import termios
import time

import pytest

from tests.runtime_helpers import ENV

pytestmark = pytest.mark.timeout(180)
LINKS = ("env->central", "env->local", "central->local", "local->env")


def _run_in_terminal(cmd: list[str], columns: int, timeout_s: float = 150) -> tuple[int, str]:
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 50, columns, 0, 0))
    env = {k: v for k, v in ENV.items() if k not in ("COLUMNS", "LINES")} | {"TERM": "xterm-256color"}
    p = subprocess.Popen(cmd, stdin=slave, stdout=slave, stderr=slave, env=env, close_fds=True)
    os.close(slave)
    out, deadline = b"", time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if select.select([master], [], [], 0.5)[0]:
            try:
                chunk = os.read(master, 65536)
            except OSError:  # the child closed the terminal
                break
            if not chunk:
                break
            out += chunk
        elif p.poll() is not None:
            break
    os.close(master)
    p.kill()
    p.wait(10)
    return p.returncode, re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", out.decode("utf-8", "replace"))


def test_the_links_table_in_an_80_column_terminal_cuts_no_link_name(tmp_path):
    code, text = _run_in_terminal([sys.executable, "-m", "hammer", "up", "--episodes", "32", "--run-dir",
                                   str(tmp_path / "run")], columns=80)
    assert code == 0 and "done: 32 episodes" in text, text[-3000:]
    header = next(line for line in text.splitlines() if "counter" in line and "env->central" in line)
    assert all(link in header for link in LINKS), header
    assert "env-…" not in text and "…" not in header
    assert max(len(line) for line in text.splitlines() if "┃" in line or "│" in line) <= 80


def test_a_wide_terminal_keeps_a_row_per_link():
    from hammer.deploy.dashboard import LinksView
    from hammer.faults.links import COLUMNS
    from rich.console import Console

    rows = {link: dict.fromkeys(COLUMNS, 123_456) for link in LINKS}
    for width, turned in ((80, True), (140, False)):
        console = Console(width=width, record=True, file=open(os.devnull, "w"))  # noqa: SIM115
        console.print(LinksView("faults: none", rows, "note"))
        text = console.export_text()
        assert "…" not in text and text.count("123,456") == 36, text
        assert ("counter" in text) == turned and all(link in text for link in LINKS)
