"""Hot update of a served team: `hammer push BUNDLE --to RUN`, `hammer rollback RUN`.

The run directory holds the update history (RUN/pushes.json, rewritten atomically) and a copy of
every pushed policy (RUN/policies/v<N>/), so a rollback never depends on a bundle that moved or
changed. The run's policy server (serve/policy_server.py) watches the history and publishes the
newest entry's weights as policy version N (then republishes it). Nothing switches on arrival:
the env host names version N in the next step's observations and global state, and every actor
holds received weights until a step names them (runtime/weights.py), so all agents change at the
same step boundary and no step is acted on with two versions. A rollback is a new version N+1
carrying the weights in effect before the latest push: same weights, same actions for the same
observations and random draws.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

from hammer.serve.bundle import BundleError, load_bundle, sha256

PUSHES = "pushes.json"
POLICIES = "policies"


def read_history(run_dir: Path) -> list[dict]:
    path = Path(run_dir) / PUSHES
    if not path.is_file():
        return []
    try:
        entries = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise BundleError(f"{path}: not valid JSON ({e}); fix: restore it or remove it to serve the first policy")
    if not isinstance(entries, list) or not all(isinstance(e, dict) and isinstance(e.get("version"), int)
                                                and isinstance(e.get("policy_dir"), str) for e in entries):
        raise BundleError(f"{path}: expected a list of {{version, policy_dir, ...}} entries")
    return entries


def _served(run_dir: Path) -> tuple[dict, dict]:
    """runtime.json and config.json of a served run (mode eval)."""
    run_dir = Path(run_dir)
    try:
        rt = json.loads((run_dir / "runtime.json").read_text())
        cfg = json.loads((run_dir / "config.json").read_text())
    except FileNotFoundError:
        raise BundleError(f"{run_dir}: no runtime.json/config.json; fix: pass the run directory `hammer serve` "
                          "printed") from None
    if rt.get("mode") != "eval":
        raise BundleError(f"{run_dir}: a training run (mode {rt.get('mode')}); fix: push to a run of `hammer serve`")
    return rt, cfg


def _write_history(run_dir: Path, entries: list[dict]) -> None:
    tmp = Path(run_dir) / (PUSHES + ".tmp")
    tmp.write_text(json.dumps(entries, indent=1))
    os.replace(tmp, Path(run_dir) / PUSHES)


def push(bundle_path: Path, run_dir: Path, trust: tuple[Path, ...] = ()) -> dict:
    """Record `bundle_path` as the next policy version of the served run; returns the history entry.
    `trust`: public keys, one of which must have signed the bundle (serve/signing.py)."""
    from hammer.learning.config import build_config

    run_dir = Path(run_dir)
    _, cfg_data = _served(run_dir)
    b = load_bundle(bundle_path, trust=trust)
    served, new = build_config(cfg_data), b.config()
    spec = json.loads((run_dir / "env_spec.json").read_text())
    b.check_env(spec)
    if (new.variant, new.wiring.msg_dim, new.wiring.has_central_network) != (
            served.variant, served.wiring.msg_dim, served.wiring.has_central_network):
        raise BundleError(f"{bundle_path}: a {new.variant} team with message length {new.wiring.msg_dim}; the run "
                          f"serves {served.variant} with {served.wiring.msg_dim}; fix: push a team of the same variant")
    entries = read_history(run_dir)
    version = (entries[-1]["version"] if entries else 0) + 1
    dst = run_dir / POLICIES / f"v{version}"
    shutil.rmtree(dst, ignore_errors=True)
    dst.mkdir(parents=True)
    for name in b.manifest["files"]:
        shutil.copyfile(b.path / name, dst / name)
    entry = {"version": version, "action": "push", "policy_dir": str(dst.resolve()), "bundle": str(Path(bundle_path).resolve()),
             "files": {n: sha256(dst / n) for n in b.manifest["files"]}, "at": time.strftime("%Y-%m-%dT%H:%M:%S")}
    _write_history(run_dir, [*entries, entry])
    return entry


def effective_stack(run_dir: Path, entries: list[dict]) -> list[dict]:
    """The policies in effect, oldest first: the served one (version 0), each push on top, each rollback
    taking the top off."""
    rt, _ = _served(run_dir)
    stack = [{"version": 0, "policy_dir": rt["policy_dir"]}]
    for e in entries:
        if e.get("action") == "rollback":
            stack.pop()
            stack[-1] = {**stack[-1], "version": e["version"]}
        else:
            stack.append(e)
    return stack


def rollback(run_dir: Path) -> dict:
    """Return the served run to the policy in effect before its latest push (as a new version)."""
    run_dir = Path(run_dir)
    entries = read_history(run_dir)
    stack = effective_stack(run_dir, entries)
    if len(stack) < 2:
        raise BundleError(f"{run_dir}: nothing to roll back (the run serves its first policy); fix: `hammer push` first")
    back = stack[-2]
    version = entries[-1]["version"] + 1
    entry = {"version": version, "action": "rollback", "policy_dir": back["policy_dir"],
             "restores_version": back["version"], "at": time.strftime("%Y-%m-%dT%H:%M:%S")}
    if "files" in back:
        entry["files"] = back["files"]
    _write_history(run_dir, [*entries, entry])
    return entry
