"""The edge install: a fresh venv with only the base distribution (no torch, PettingZoo, matplotlib) runs
`hammer local --bundle` inside a real served run on 127.0.0.1, and the CLI names the extra a training
command needs. The venv (benchmarks.edge_venv: the project with --no-deps, then its
base dependencies) is the session's `edge_venv` fixture (tests/conftest.py); tests/test_netns.py runs it
across network namespaces."""

from __future__ import annotations

import subprocess

import pytest
from hammer.benchmarks.edge_venv import clean_env
from hammer.deploy.launcher import launch
from hammer.protocol.session import free_loopback_port
from hammer.serve.bundle import load_bundle
from hammer.serve.served_settings import serve_settings

from tests.runtime_helpers import trained_bundle

pytestmark = pytest.mark.timeout(240)


def _served_with_edge_agent(hammer: str, bundle, tmp_path, agent: int, episodes: int):
    """The bundle served on 127.0.0.1 with agent `agent` from `hammer local --bundle` of that install:
    (the run's result, the agent's output, its exit status)."""
    port = free_loopback_port()
    settings, _ = serve_settings(bundle, f"edge-{agent}", runtime=[f"hub_port={port}"])
    edge = subprocess.Popen([hammer, "local", "--bundle", str(bundle.path), "--agent", str(agent), "--run-id",
                             f"edge-{agent}", "--connect", f"tcp/127.0.0.1:{port}"], env=clean_env(), cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        res = launch(bundle.config(episodes=episodes, msg_dropout=0.0), settings, tmp_path / "served",
                     external_agents=(agent,))
        out, _ = edge.communicate(timeout=30)
    finally:
        if edge.poll() is None:
            edge.kill()
    return res, out, edge.returncode


def test_an_edge_only_install_serves_in_a_real_run(tmp_path, edge_venv):
    py = str(edge_venv)
    env = clean_env()  # the venv's install, not this checkout
    probe = "import importlib.util as u; print([m for m in ('torch', 'pettingzoo', 'matplotlib', 'mpe2', 'scipy', 'supersuit', 'gymnasium') if u.find_spec(m)])"
    missing = subprocess.run([py, "-c", probe],
                             capture_output=True, text=True, env=env, cwd=tmp_path, check=True)
    assert missing.stdout.strip() == "[]"
    hammer = str(edge_venv.parent / "hammer")
    assert subprocess.run([hammer, "--help"], check=False, capture_output=True, env=env, cwd=tmp_path).returncode == 0
    r = subprocess.run([hammer, "train", "--episodes", "1"], check=False, capture_output=True, text=True, env=env, cwd=tmp_path)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "pip install 'hammer-marl[train]'" in r.stderr

    bundle = load_bundle(trained_bundle(tmp_path, episodes=16))
    r = subprocess.run([hammer, "play", str(bundle.path), "--out", "team.gif"], check=False, capture_output=True,
                       text=True, env=env, cwd=tmp_path)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "pip install 'hammer-marl[train]'" in r.stderr
    res, out, code = _served_with_edge_agent(hammer, bundle, tmp_path, agent=2, episodes=16)
    assert res.summary["completed"] and res.summary["episodes"] == 16
    assert code == 0, out
    assert "'steps': 50," in out and "'weights_loaded': 1" in out  # 16 episodes on 8 copies: 2 x 25 steps
    assert res.links["local->env"]["defaults"] == 0  # every action of agent 2 came from the edge venv in time


def test_the_edge_install_runs_on_python_3_13(tmp_path):
    """Debian 13's Python: the base install (the session's wheel, which is for any Python 3) and an edge
    agent from it in a served run (skipped where no python3.13 is on PATH)."""
    import os
    import shutil
    from pathlib import Path

    from hammer.benchmarks.edge_venv import EdgeVenvError, build_edge_venv

    from tests.runtime_helpers import hammer_wheel

    pyenv = Path(os.environ.get("PYENV_ROOT", Path.home() / ".pyenv")) / "versions"
    found = [shutil.which("python3.13"), *map(str, sorted(pyenv.glob("3.13*/bin/python3.13")))]
    works = [p for p in found if p and subprocess.run(
        [p, "-c", "import sys; assert sys.version_info[:2] == (3, 13)"], check=False, capture_output=True,
        env=clean_env()).returncode == 0]
    if not works:
        pytest.skip("no python3.13 interpreter (PATH, pyenv)")
    py313 = works[0]
    try:
        py = build_edge_venv(tmp_path / "venv313", compile_pyc=False, python=py313, wheel=hammer_wheel(tmp_path),
                             own_pip=False)
    except EdgeVenvError as e:
        if e.offline:
            pytest.skip(f"the package index is unreachable: {e}")
        raise
    env = clean_env()
    assert subprocess.run([str(py), "-c", "import sys; assert sys.version_info[:2] == (3, 13)"], check=False,
                          env=env).returncode == 0
    bundle = load_bundle(trained_bundle(tmp_path, episodes=16))
    res, out, code = _served_with_edge_agent(str(py.parent / "hammer"), bundle, tmp_path, agent=0, episodes=8)
    assert res.summary["completed"] and code == 0, out
    assert res.links["local->env"]["defaults"] == 0
