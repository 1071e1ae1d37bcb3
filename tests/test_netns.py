"""The edge chain across Linux network namespaces (tests/harness/edge_chain.py, benchmarks/netns.py): a
briefly trained team (the session's, tests/runtime_helpers.trained_run: the chain's `hammer train` step is
the same training in a process of its own), exported with `hammer export`, served with `hammer serve` in the hub namespace
(router, env host, policy server), its central agent in a namespace of its own and each edge agent
(`hammer local --bundle`, from a torch-free venv) in its own, joined by veth pairs with addresses private
to them, agent 0's link limited with tc tbf; a hot update (`hammer push`) and a rollback (`hammer rollback`)
land mid-run through the CLI; `hammer play` renders the team. Namespaces are created and deleted here."""

from __future__ import annotations

import os
import shutil
import subprocess

import numpy as np
import pytest
from hammer.benchmarks.netns import NetnsUnavailable
from safetensors.numpy import load_file, save_file

from tests.harness.edge_chain import chain, replay_check, summary_lines
from tests.runtime_helpers import SHORT_RUN, netns_reason, trained_run

pytestmark = pytest.mark.timeout(300)




def _update_of(run, out):
    """Team B: team A with a random, sharp action head and other central weights (a briefly trained
    head is near uniform), so B acts and messages clearly differently on the same inputs."""
    shutil.copytree(run, out)
    rng = np.random.default_rng(0)
    for name in ("local", "central"):
        f = str(out / "final" / f"{name}.safetensors")
        w = load_file(f)
        key = (f"actor.layers.{max(int(k.split('.')[2]) for k in w if k.startswith('actor.layers.'))}.weight"
               if name == "local" else max(w, key=lambda k: w[k].size))
        w[key] = rng.normal(0.0, 3.0, w[key].shape).astype(np.float32)
        save_file(w, f)
    return out


def test_the_chain_across_namespaces_from_a_torch_free_venv(tmp_path, edge_venv):
    reason = netns_reason(("ip", "tc"))
    if reason:
        pytest.skip(reason)
    a = trained_run(tmp_path / "a", (*SHORT_RUN, "episodes=16", "seed=4"))
    b = _update_of(a, tmp_path / "b")
    tag = f"t{os.getpid() % 10000}"
    try:
        # 1,250 steps: a push is pulled in chunks before it is named, and on a loaded machine each of
        # the push and the rollback (a CLI start each) can take a couple of hundred steps
        r = chain(tmp_path / "chain", a, b, edge_venv, rates=(1024,), episodes=400, tag=tag)
    except NetnsUnavailable as e:
        pytest.skip(str(e))
    run = r["runs"][0]
    assert run["completed"] and run["edge_exit_codes"] == [0, 0, 0], run
    assert run["steps"] == 1250 and run["default_actions"] == 0 and run["off_policy_actions"] == 0
    assert set(run["bytes_per_step"]) == {"local-0", "local-1", "local-2", "central"}
    assert all(x > 300 for x in run["bytes_per_step"].values()), run  # each step crossed every link
    up = run["updates"]
    assert "error" not in up["driver"], up
    assert set(up["steps_per_version"]) == {0, 1, 2} and min(up["steps_per_version"].values()) > 20, up
    assert up["versions_monotone"] and up["no_step_missed"], up
    assert run["replay"]["acted_in_time"] > 0.99
    assert run["replay"]["match"] == 1.0, run["replay"]  # one version per step; after the rollback A exactly
    bundle_a = tmp_path / "chain" / "bundle-a"
    only_a = replay_check(tmp_path / "chain" / "netns" / "served-1024" / "trace.npz", {0: bundle_a, 1: bundle_a,
                                                                                       2: bundle_a})
    assert only_a["match_per_version"][1] < 0.7  # B did act differently in its window
    assert (tmp_path / "chain" / "team.gif").stat().st_size > 10_000 and "25 frames" in r["play"]
    said = summary_lines(r, tmp_path / "chain")  # what `make edge-chain` prints: a line per step, no JSON
    assert said[1].startswith("served, agent 0's link 1024 kbit/s: completed, 400 episodes")
    assert "push and rollback: steps acted per version v0 " in said[2] and "no step missed: True" in said[2]
    assert said[3].startswith("  replay with each version's weights: 100.0% of the actions match")
    assert not any(line.lstrip().startswith(("{", "}", '"')) for line in said)
    left = subprocess.run(["ip", "netns", "list"], check=False, capture_output=True, text=True).stdout
    assert f"hmr{tag}" not in left  # everything the test created is gone
