"""A fresh venv with only the edge install of hammer: what an edge machine would have.

    python -m hammer.benchmarks.edge_venv PATH        (prints the venv's python)

Built with pip: the project (from this checkout, not an editable link) with --no-deps, then exactly
its base dependencies from pyproject.toml, so nothing of the `train` extra (torch, PettingZoo,
matplotlib, ...) can come in through a transitive requirement. Used by `tests/test_edge_install.py`,
`tests/test_netns.py` and `tests/harness/edge_chain.py` (edge agents that run without torch).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# pip's words for "the package index could not be reached" (then a test skips instead of failing).
OFFLINE_SIGNS = ("No matching distribution", "Could not find a version", "Failed to establish a new connection",
                 "Temporary failure in name resolution", "Network is unreachable", "ConnectionError", "timed out")


class EdgeVenvError(RuntimeError):
    """The venv could not be built; `offline` says whether the package index was unreachable."""

    def __init__(self, msg: str, offline: bool) -> None:
        super().__init__(msg)
        self.offline = offline


def clean_env() -> dict[str, str]:
    """The environment for a process of the edge venv: no PYTHONPATH, so it runs the venv's install
    and not this checkout."""
    return {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}


def build_edge_venv(path: Path, project: Path = ROOT, timeout_s: float = 180, compile_pyc: bool = True,
                    python: str | Path = sys.executable, wheel: Path | None = None, own_pip: bool = True) -> Path:
    """Make `path` a venv with only the base install of `project`; returns its python.
    Reuses a venv already built there from the same sources (its marker file). compile_pyc=False:
    pip skips byte-compiling (quicker to build; the first imports compile what they load).
    `python`: the interpreter of the venv (e.g. a python3.13, what Debian 13 ships).
    `wheel`: a wheel already built from `project` (build_wheel), installed as it is; default: pip
    builds one from a copy of the sources. own_pip=False: the venv gets no pip of its own and this
    interpreter's pip installs into it (`pip --python`), which skips bootstrapping pip there."""
    path = Path(path)
    py = path / "bin" / "python"
    marker, stamp = path / ".hammer-edge", f"{python} {source_stamp(project)}"
    if py.is_file() and marker.is_file() and marker.read_text() == stamp:
        return py
    subprocess.run([str(python), "-m", "venv", "--clear", *([] if own_pip else ["--without-pip"]), str(path)],
                   check=True, timeout=60, env=clean_env())
    base = tomllib.loads((project / "pyproject.toml").read_text())["project"]["dependencies"]
    pip = [*([str(py), "-m", "pip"] if own_pip else [sys.executable, "-m", "pip", "--python", str(py)]),
           "install", "-q", "--disable-pip-version-check", *([] if compile_pyc else ["--no-compile"])]
    with tempfile.TemporaryDirectory(prefix="hammer-src-") as tmp:
        src = wheel or source_copy(project, Path(tmp) / "src")
        for args in (["--no-deps", str(src)], base):
            r = subprocess.run([*pip, *args], check=False, timeout=timeout_s, capture_output=True, text=True,
                               env=clean_env())
            if r.returncode != 0:
                err = (r.stderr.strip().splitlines() or ["(no output)"])[-1]
                raise EdgeVenvError(f"pip install {' '.join(args)[:80]} failed: {err}",
                                    offline=any(s in r.stderr for s in OFFLINE_SIGNS))
    marker.write_text(stamp)
    return py


def build_wheel(dest: Path, project: Path = ROOT, timeout_s: float = 300) -> Path:
    """The wheel of `project` (no dependencies), built into `dest` by this interpreter's pip with its own
    setuptools (no isolated build environment to set up); returns its path."""
    with tempfile.TemporaryDirectory(prefix="hammer-src-") as tmp:
        src = source_copy(project, Path(tmp) / "src")
        subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w",
                        str(dest), str(src)], check=True, capture_output=True, timeout=timeout_s)
    return next(Path(dest).glob("hammer_marl-*.whl"))


def source_copy(project: Path, dest: Path) -> Path:
    """The files a build of `project` needs, copied to `dest`: pip builds in the source tree, and a
    stale build/ there (an older layout's packages) would end up in the wheel."""
    import shutil

    shutil.copytree(project, dest, ignore=shutil.ignore_patterns(
        ".venv", "build", ".git", "runs", "docs", "__pycache__", "*.egg-info", "tests", "dist"))
    return dest


def source_stamp(project: Path) -> str:
    """The project and a digest of its sources' names, sizes and times: a venv built from other code is rebuilt."""
    import hashlib

    h = hashlib.sha256()
    for f in sorted([project / "pyproject.toml", *project.glob("*/**/*.py")]):
        if ".venv" not in f.parts and "build" not in f.parts:
            st = f.stat()
            h.update(f"{f.relative_to(project)} {st.st_size} {st.st_mtime_ns}\n".encode())
    return f"{project.resolve()} {h.hexdigest()}"


def main() -> None:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("path", type=Path)
    a = ap.parse_args()
    try:
        print(build_edge_venv(a.path))
    except EdgeVenvError as e:
        sys.exit(f"error: {e}")


if __name__ == "__main__":
    main()
