"""One import package: the wheel, installed (not editable) into a fresh venv, puts exactly
one top-level import package into site-packages, and `hammer up` and an edge agent run from a
research project's folder that holds packages of its own named like hammer's parts. Each of those
packages raises on import, so any shadowing fails the run loudly.

The fresh venv takes hammer from the wheel alone; its other dependencies (torch, PettingZoo, ...)
come from this interpreter's site-packages through a path file, so nothing is downloaded: a path
added that way is not scanned for .pth files, so this checkout's editable install stays out of it.
"""

from __future__ import annotations

import site
import subprocess
import sys
import venv
from pathlib import Path

import pytest
from hammer.benchmarks.edge_venv import clean_env
from hammer.protocol.session import free_loopback_port

from tests.runtime_helpers import hammer_wheel

pytestmark = pytest.mark.timeout(600)

SHADOWS = ("experiments", "learning", "protocol", "deploy", "envs", "runtime", "benchmarks", "serve", "faults")


@pytest.fixture(scope="module")
def wheel_venv(tmp_path_factory):
    """(python, site-packages) of a fresh venv with hammer installed from its wheel (the session's:
    tests/runtime_helpers.hammer_wheel), by this interpreter's pip (the venv needs none of its own)."""
    d = tmp_path_factory.mktemp("wheel")
    wheel = hammer_wheel(d / "dist")
    venv.EnvBuilder(with_pip=False).create(d / "venv")
    py = d / "venv" / "bin" / "python"
    sp = d / "venv" / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
    # every site-packages this interpreter reads (a venv's own, or the ones a path file of it adds)
    deps = [p for p in sys.path if p.endswith("site-packages") and Path(p).is_dir()] or site.getsitepackages()
    (sp / "hammer-deps.pth").write_text("\n".join(deps) + "\n")
    subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "-q", "--no-deps", "--no-index",
                    str(wheel)], check=True, capture_output=True, timeout=300)
    return py, sp


@pytest.fixture()
def project(tmp_path):
    """A research project's folder with packages of its own, each named like a part of hammer."""
    for name in SHADOWS:
        (tmp_path / name).mkdir()
        (tmp_path / name / "__init__.py").write_text(
            f"raise ImportError('the project\\'s own {name}/ was imported: it shadows hammer')\n")
    return tmp_path


def test_the_wheel_installs_one_import_package(wheel_venv):
    py, sp = wheel_venv
    record = next(sp.glob("hammer_marl-*.dist-info")) / "RECORD"
    top = {line.split(",")[0].split("/")[0] for line in record.read_text().splitlines()}
    assert {t for t in top if not t.endswith(".dist-info") and t != ".."} == {"hammer"}, top
    where = subprocess.run([str(py), "-c", "import hammer.protocol.session as s; print(s.__file__)"],
                           capture_output=True, text=True, check=True, env=clean_env(), cwd=sp.parent)
    assert where.stdout.strip().startswith(str(sp / "hammer" / "protocol")), where.stdout


def test_hammer_up_and_an_edge_agent_run_from_a_project_with_packages_of_the_same_names(wheel_venv, project):
    py, _ = wheel_venv
    hammer = str(py.parent / "hammer")
    env = clean_env()
    up = subprocess.run([hammer, "up", "--episodes", "32", "--variant", "hammer", "--run-dir", "run", "--no-dashboard"],
                        check=False, capture_output=True, text=True, env=env, cwd=project, timeout=300)
    assert up.returncode == 0, up.stderr[-3000:]
    assert up.stdout.startswith("done: 32 episodes")
    assert not any("shadows hammer" in p.read_text() for p in (project / "run" / "logs").glob("*.log"))

    exp = subprocess.run([hammer, "export", "run", "--out", "bundle"], check=False, capture_output=True, text=True, env=env,
                         cwd=project, timeout=120)
    assert exp.returncode == 0, exp.stderr[-2000:]
    port = free_loopback_port()
    serve = subprocess.Popen([hammer, "serve", "bundle", "--episodes", "32", "--external", "1", "--runtime",
                              f"hub_port={port}", "--run-dir", "served", "--no-dashboard"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=project)
    # `python -m hammer` puts the project's folder first on sys.path: the strictest way to start it
    edge = subprocess.Popen([str(py), "-m", "hammer", "local", "--bundle", "bundle", "--agent", "1", "--run-id",
                             "served", "--connect", f"tcp/127.0.0.1:{port}"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=project)
    try:
        _, err = serve.communicate(timeout=240)
        edge_out, _ = edge.communicate(timeout=60)
    finally:
        for p in (serve, edge):
            if p.poll() is None:
                p.kill()
    assert serve.returncode == 0, err[-3000:]
    assert edge.returncode == 0, edge_out[-3000:]
    assert "shadows hammer" not in edge_out and "'steps': 25," in edge_out  # 32 episodes on 32 copies
