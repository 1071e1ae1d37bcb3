"""Helpers shared by the tests that start real `hammer` processes."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path

import psutil

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "HAMMER_TORCH_THREADS": "1"}


def hammer(*args: str, timeout: float = 300, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """Run `hammer ARGS` as a fresh interpreter from the repository root (one torch thread), with
    `env` added to the environment."""
    return subprocess.run([sys.executable, "-m", "hammer.cli", *args], check=False, capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT, env={**ENV, **(env or {})})


# Settings that make this CPU run other maths kernels than it picks itself, as another CPU would:
# glibc's libm without its FMA/AVX2 variants (exp, log), numpy's SIMD loops at the x86-64-v2
# baseline (exp, tanh), numpy's OpenBLAS with the Sandy Bridge kernels, torch's ATen without
# vector kernels, MKL and oneDNN at SSE4.2. A result one of them changes depends on the CPU
# (tests/test_exactness.py). Unknown names are ignored by each library; x86-64 only.
DISPATCH: dict[str, dict[str, str]] = {"default": {}}
if platform.machine().lower() in ("x86_64", "amd64"):
    DISPATCH["libm without FMA"] = {"GLIBC_TUNABLES": "glibc.cpu.hwcaps=-FMA,-AVX2,-AVX512F"}
    DISPATCH["baseline kernels"] = {
        "GLIBC_TUNABLES": "glibc.cpu.hwcaps=-FMA,-AVX2,-AVX512F", "NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4",
        "OPENBLAS_CORETYPE": "Sandybridge", "ATEN_CPU_CAPABILITY": "default", "MKL_ENABLE_INSTRUCTIONS": "SSE4_2",
        "ONEDNN_MAX_CPU_ISA": "SSE41"}


def processes_mentioning(text: str) -> list[psutil.Process]:
    """Live processes whose command line contains `text` (e.g. a run directory): strays."""
    found = []
    for p in psutil.process_iter(["cmdline"]):
        try:
            if any(text in part for part in (p.info["cmdline"] or [])):
                found.append(p)
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            pass
    return found


def netns_reason(tools: tuple[str, ...] = ("ip",)) -> str | None:
    """Why network namespaces cannot be made here (a test skips with it), or None: root, the
    iproute2 `tools`, and a kernel that lets us add a namespace."""
    import shutil

    if os.geteuid() != 0 or any(shutil.which(t) is None for t in tools):
        return f"needs root and iproute2 ({', '.join(tools)}) to create network namespaces"
    name = f"hmrprobe{os.getpid() % 100000}"
    r = subprocess.run(["ip", "netns", "add", name], check=False, capture_output=True, text=True)
    if r.returncode != 0:
        return f"cannot create a network namespace here: {r.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", name], check=False, capture_output=True)
    return None


# Where trained teams, `hammer up` runs and the wheel are kept for the whole session (tests/conftest.py
# sets it; every xdist worker inherits it), so that modules building the same thing build it once.
TEAMS_ENV = "HAMMER_TEST_TEAMS"
SHORT_RUN = ("num_envs=8", "rollout_steps=25", "epochs=1", "minibatches=2")
# `hammer train --preset cn3 --variant hammer --central-mode rl` as the runtime tests run it (the
# CLI takes HAMMER_TORCH_THREADS=1 from ENV): the trainer reference that `hammer up` must equal.
CN3_RL = ("variant=hammer", "central_mode=rl", "torch_threads=1")
# The team several modules compare against: the float32 rl run without absences or a local view,
# with its TensorBoard events; a shorter run's episodes are its first ones (no schedule depends on
# the episode budget).
CN3_RL_100 = (*CN3_RL, "episodes=100")
# The networks of the tests that torch.compile: one hidden layer of 16 each, not the presets' two.
# A compile's cost (inductor's codegen and the C++ build, per graph, on a cold cache in CI) grows
# with the layers the graph steps through (forward, backward, clip, Adam per tensor); what those
# tests check (compiled = eager, the device, bf16, seed batches) does not depend on the depth.
COMPILE_NETS = ("actor_hidden=[16]", "critic_hidden=[16]", "central_hidden=[16]")


def made_once(key: str, make) -> Path | None:
    """The session's one copy of what `make(path)` writes at a path, made by the first worker that
    asks, under a file lock in the shared cache (TEAMS_ENV); None outside such a session."""
    import fcntl
    import shutil

    cache = os.environ.get(TEAMS_ENV)
    if not cache:
        return None
    kept = Path(cache) / key / "run"
    kept.parent.mkdir(parents=True, exist_ok=True)
    with open(kept.parent / "lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another worker may be making it now
        if not (kept.parent / "done").exists():
            shutil.rmtree(kept, ignore_errors=True)
            make(kept)
            (kept.parent / "done").touch()
    return kept


def _kept(run: Path, key: tuple, make) -> Path:
    """`make(d)` builds a run directory at `d`; each distinct `key` is built once a session
    (`made_once`) and copied to `run`: the copy is the test's own to change."""
    import hashlib
    import shutil

    kept = made_once(hashlib.sha256(repr(key).encode()).hexdigest()[:16], make)
    if kept is None:
        make(run)
        return run
    shutil.copytree(kept, run)
    return run


def trained_run(run: Path, overrides: tuple[str, ...], preset: str = "cn3", tensorboard: bool = False) -> Path:
    """A run directory at `run` of an in-process `hammer train` of `preset` with `overrides` (and its
    TensorBoard events with `tensorboard`), trained once a session (`_kept`)."""
    from hammer.learning.config import merge_config
    from hammer.learning.rundir import RunDir
    from hammer.learning.trainer import train

    def train_at(d: Path) -> None:
        cfg = merge_config(preset, overrides=list(overrides))
        train(cfg, RunDir.create(d, cfg), tensorboard=tensorboard)

    return _kept(run, (preset, tuple(overrides), *(("tb",) if tensorboard else ())), train_at)


# `hammer up` of cn3 in backprop mode, 100 episodes, with deadlines generous enough that a loaded
# machine turns no slow message into a fallback: the one-process-per-agent run that both
# test_runtime_up (against the trainer) and test_local_pool (against pooled agents) compare with.
UP_CN3_BACKPROP = ("--episodes", "100", "--central-mode", "backprop", "--no-dashboard",
                   "--runtime", "msg_deadline_ms=5000", "--runtime", "act_deadline_ms=10000")


# `hammer up` of cn3 in rl mode, 70 episodes (two updates), with the set central network and a local
# view of radius 0.6: the run that test_runtime_up (the set net) and test_local_view (the view) each
# compare with the trainer. The view masks only the local agents' inputs and the set net is only the
# central agent's forward (its state stays full), so neither changes what the other's check sees.
UP_CN3_SET_VIEW = ("--episodes", "70", "--central-mode", "rl", "--set", "central_net=set",
                   "--set", "env_kwargs.obs_radius=0.6", "--no-dashboard",
                   "--runtime", "msg_deadline_ms=5000", "--runtime", "act_deadline_ms=10000")
CN3_SET_VIEW = (*CN3_RL, "central_net=set", "env_kwargs.obs_radius=0.6")


def up_cn3(mode: str) -> tuple[str, ...]:
    """UP_CN3_BACKPROP's run in central mode `mode` (the session runs each mode's once)."""
    return tuple(a.replace("backprop", mode) for a in UP_CN3_BACKPROP)


def up_run(run: Path, args: tuple[str, ...]) -> Path:
    """A run directory at `run` of `hammer up ARGS` (a fresh CLI process, as a user starts it), run
    once a session (`_kept`); its stdout is kept as `up.out` in the run directory. No process of the
    run may outlive the CLI (the run directory is on every role's command line)."""

    def up_at(d: Path) -> None:
        r = hammer("up", *args, "--run-dir", str(d))
        assert r.returncode == 0, r.stderr[-2000:]
        assert processes_mentioning(str(d)) == [], "a process of the run outlived hammer up"
        (d / "up.out").write_text(r.stdout)

    return _kept(run, ("up", tuple(args)), up_at)


def _maps_torch(pid: int) -> bool:
    return any("libtorch" in m.path for m in psutil.Process(pid).memory_maps())


def pipelined_run(run: Path) -> Path:
    """A run directory at `run` of `hammer up` of cn3 (rl mode) for 320 episodes with
    max_policy_lag=1 and generous deadlines, the launcher in this process, run once a session
    (`_kept`): test_runtime_up judges its pipelined rollouts, test_runtime_edge which roles load
    torch, which the run records in `torch_maps.json` (role -> libtorch mapped) from one look at
    every role's memory maps while it ran (320 episodes: long enough to be looked at before the roles
    exit). No process of the run may outlive the launcher."""
    import json

    from hammer.deploy.launcher import launch
    from hammer.learning.config import merge_config
    from hammer.runtime.settings import RuntimeSettings

    def launch_at(d: Path) -> None:
        seen: dict[str, bool] = {}

        def inspect(sup, board) -> None:
            """All five roles at one tick, or none: a role not started yet, or already exiting (a
            zombie on a loaded machine), is looked at again at the next tick."""
            if seen or len(board.heartbeats) < 3:
                return
            maps = {}
            for name in ("local-0", "local-2", "central", "env", "learner"):
                pid = sup.pid(name)
                if pid is None:
                    return
                try:
                    maps[name] = _maps_torch(pid)
                except psutil.NoSuchProcess:  # ZombieProcess included
                    return
            seen.update(maps)

        cfg = merge_config("cn3", overrides=["episodes=320", "central_mode=rl"])
        settings = RuntimeSettings(run_id="pipelined", max_policy_lag=1, msg_deadline_ms=5000, act_deadline_ms=10000)
        res = launch(cfg, settings, d, chaos=inspect)
        assert res.summary["completed"]
        assert processes_mentioning(str(d)) == [], "a process of the run outlived the launcher"
        (d / "torch_maps.json").write_text(json.dumps(seen))

    return _kept(run, ("pipelined",), launch_at)


def hammer_wheel(directory: Path) -> Path:
    """The wheel of this checkout (benchmarks.edge_venv.build_wheel), built once a session for every
    test that installs it; outside a session, built into `directory`."""
    from hammer.benchmarks.edge_venv import build_wheel

    kept = made_once("wheel", lambda d: build_wheel(d))
    return next(kept.glob("hammer_marl-*.whl")) if kept is not None else build_wheel(directory)


def trained_bundle(directory: Path, episodes: int) -> Path:
    """A briefly trained cn3 team (8 env copies, seed 4) exported as a bundle under `directory`."""
    from hammer.serve.bundle import export_bundle

    trained_run(directory / "run", (*SHORT_RUN, f"episodes={episodes}", "seed=4"))
    return export_bundle(directory / "run", directory / "bundle").path


def trained_pair(directory: Path, episodes: int = 16) -> tuple[Path, Path]:
    """`trained_bundle`, and the same team with its local weights moved by 0.01, exported declaring
    that it works with the first one's central network: a push that must be pulled in chunks."""
    import shutil

    import numpy as np
    from hammer.serve.bundle import export_bundle
    from safetensors.numpy import load_file, save_file

    a = trained_bundle(directory, episodes=episodes)
    shutil.copytree(directory / "run", directory / "run-b")
    final = directory / "run-b" / "final"
    w = load_file(str(final / "local.safetensors"))
    save_file({k: v + np.float32(0.01) for k, v in w.items()}, str(final / "local.safetensors"))
    return a, export_bundle(directory / "run-b", directory / "B", works_with=(directory / "run" / "final",)).path


def run_block_beside_serve(command: str, code: str, folder: Path, run_name: str, port: str
                           ) -> tuple[subprocess.CompletedProcess, subprocess.Popen, str]:
    """A docs' Python block run as it stands against the `hammer serve ...` command the docs name
    (port made `port`), both from the user's `folder`: the block starts once the fleet's central agent
    is up; then SIGTERM to `hammer serve`. Returns the block's result, the server and its output."""
    import signal
    import time

    serve = subprocess.Popen([sys.executable, "-P", "-m", "hammer.cli", *command.replace("7447", port).split()[1:]],
                             cwd=folder, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        # the block starts once the central agent is up (on a loaded machine the launcher takes seconds)
        central_log = folder / "runs" / run_name / "logs" / "central.log"
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and "central alive" not in (
                central_log.read_text() if central_log.is_file() else ""):
            assert serve.poll() is None, "hammer serve exited before its central agent was up"
            time.sleep(0.1)
        r = subprocess.run([sys.executable, "-c", code.replace("7447", port)], cwd=folder, env=ENV,
                           capture_output=True, text=True, timeout=120, check=False)
    finally:
        serve.send_signal(signal.SIGTERM)
        out = serve.communicate(timeout=60)[0].decode()
    return r, serve, out
