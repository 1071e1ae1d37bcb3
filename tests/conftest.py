"""Fixtures shared by test files."""

from __future__ import annotations

import signal

import pytest

# Tests stop real processes with SIGINT (Ctrl-C, as a person would). A shell that starts a job in
# the background (`make test &`, nohup) leaves SIGINT ignored, children inherit an ignored signal
# across exec, and Python then never turns it into KeyboardInterrupt: those stops would silently not
# happen. A handled signal is reset to the default at exec, so handling it here gives every child
# the terminal's Ctrl-C again, whatever launched the suite.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(scope="session")
def edge_venv(tmp_path_factory):
    """The python of a fresh venv with only the edge install of this checkout (benchmarks.edge_venv),
    built once per session; skipped only when the package index is unreachable."""
    from hammer.benchmarks.edge_venv import EdgeVenvError, build_edge_venv

    try:
        return build_edge_venv(tmp_path_factory.mktemp("edge") / "venv", compile_pyc=False)  # quicker to build
    except EdgeVenvError as e:
        if e.offline:
            pytest.skip(f"the package index is unreachable, so no edge venv can be built: {e}")
        raise
