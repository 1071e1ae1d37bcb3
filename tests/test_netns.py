"""A served team across Linux network namespaces (benchmarks/netns.py): the hub namespace (router,
env host, central agent, policy server) and one namespace per edge agent, joined by veth pairs with
addresses private to them, agent 0's link limited with tc tbf. Created and deleted by the test."""

from __future__ import annotations

import os
import shutil
import subprocess

import pytest

from benchmarks.netns import NetnsUnavailable, served_run
from learning.config import merge_config
from learning.rundir import RunDir
from learning.trainer import train
from serve.bundle import export_bundle

pytestmark = pytest.mark.timeout(240)


def _netns_reason() -> str | None:
    if os.geteuid() != 0 or shutil.which("ip") is None or shutil.which("tc") is None:
        return "needs root and iproute2 (ip, tc) to create network namespaces"
    name = f"hmrprobe{os.getpid() % 100000}"
    r = subprocess.run(["ip", "netns", "add", name], check=False, capture_output=True, text=True)
    if r.returncode != 0:
        return f"cannot create a network namespace here: {r.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", name], check=False, capture_output=True)
    return None


def test_a_served_team_runs_across_namespaces_with_a_limited_link(tmp_path):
    reason = _netns_reason()
    if reason:
        pytest.skip(reason)
    cfg = merge_config("cn3", overrides=["num_envs=8", "rollout_steps=25", "epochs=1", "episodes=16", "seed=1"])
    train(cfg, RunDir.create(tmp_path / "run", cfg), tensorboard=False)
    bundle = export_bundle(tmp_path / "run", tmp_path / "bundle")
    tag = f"t{os.getpid() % 10000}"
    try:
        r = served_run(bundle.path, tmp_path / "ns", episodes=16, rate_kbit=1024, tag=tag)
    except NetnsUnavailable as e:
        pytest.skip(str(e))
    assert r["completed"] and r["edge_exit_codes"] == [0, 0, 0], r
    assert r["steps"] == 50 and r["default_actions"] == 0
    assert all(b > 500 for b in r["bytes_per_step"]), r  # every step's obs, message and action crossed each link
    left = subprocess.run(["ip", "netns", "list"], check=False, capture_output=True, text=True).stdout
    assert f"hmr{tag}" not in left  # everything the test created is gone
