"""Fixtures shared by test files."""

from __future__ import annotations

import pytest


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
