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

A realtime fleet (`hammer serve --realtime`, deploy/fleet_launch.py) takes pushes and rollbacks too: its
launcher writes the same files and runs the same policy server. It has no step to name a version
at, so each robot and the central agent switch on their own once they hold it (docs/fleet.md);
for a while some robots act with the new local policy on the old central network's messages, or
the other way round, so a fleet push is paired-checked as a canary is (`check_central_pairing`),
and a staged rollout (`--canary`) is refused: the fleet's world writes no health.json to gate on.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

from hammer.runtime.pushes import PUSHES, RECORD_ONLY, HistoryError, assignment, read_pushes
from hammer.serve.bundle import BundleError, load_bundle, sha256

POLICIES = "policies"


def read_history(run_dir: Path) -> list[dict]:
    try:
        return read_pushes(run_dir)
    except HistoryError as e:
        raise BundleError(str(e)) from None


def _served(run_dir: Path) -> tuple[dict, dict]:
    """runtime.json and config.json of a served run (mode eval)."""
    run_dir = Path(run_dir)
    try:
        rt = json.loads((run_dir / "runtime.json").read_text())
        cfg = json.loads((run_dir / "config.json").read_text())
    except FileNotFoundError:
        if (run_dir / "fleet.json").is_file():
            raise BundleError(f"{run_dir}: a realtime fleet started without a policy server (by an older hammer) "
                              "takes no pushes; fix: restart the fleet with this hammer, or its robots with the new "
                              "bundle (docs/fleet.md)") from None
        raise BundleError(f"{run_dir}: no runtime.json/config.json; fix: pass the run directory `hammer serve` "
                          "printed") from None
    if rt.get("mode") != "eval":
        raise BundleError(f"{run_dir}: a training run (mode {rt.get('mode')}); fix: push to a run of `hammer serve`")
    return rt, cfg


def refuse_stopped(run_dir: Path, what: str = "push") -> None:
    """A served run that has ended (its launcher wrote summary.json: budget spent, SIGTERM, Ctrl-C) takes
    no push or rollback: nothing would serve it, and serving the folder again sets this session's history
    aside and starts from the bundle given (deploy/launcher.py `set_aside_served_session`), so it would be lost."""
    path = Path(run_dir) / "summary.json"
    if not path.is_file():
        return
    try:
        s = json.loads(path.read_text())
    except (OSError, ValueError):
        s = {}
    how = "it spent its budget" if s.get("completed") else f"stopped by {s.get('stopped_by') or 'its launcher'}"
    fix = ("serve the new bundle: hammer serve BUNDLE --run-dir " + str(run_dir) if what == "push"
           else "serve the bundle wanted: hammer serve BUNDLE --run-dir " + str(run_dir))
    raise BundleError(f"{run_dir}: the served run has ended ({how}; summary.json), so a {what} would reach nothing, "
                      f"and serving the folder again starts from the bundle it is given; fix: {fix}")


def is_fleet(run_dir: Path) -> bool:
    """A realtime fleet's run directory (its launcher writes fleet.json)."""
    return (Path(run_dir) / "fleet.json").is_file()


def append_entry(run_dir: Path, entry: dict) -> dict:
    """Append one entry to the history (read, append, replace atomically); returns it."""
    _write_history(run_dir, [*read_history(run_dir), entry])
    return entry


def _write_history(run_dir: Path, entries: list[dict]) -> None:
    tmp = Path(run_dir) / (PUSHES + ".tmp")
    tmp.write_text(json.dumps(entries, indent=1))
    os.replace(tmp, Path(run_dir) / PUSHES)


def push(bundle_path: Path, run_dir: Path, trust: tuple[Path, ...] = (), agents: list[int] | None = None) -> dict:
    """Record `bundle_path` as the next policy version of the served run; returns the history entry.
    `trust`: public keys, one of which must have signed the bundle (serve/signing.py). `agents`:
    a canary (serve/canary.py): only these agents switch; the others and the central agent stay on
    the version in effect, which the bundle's local policy must declare it works with."""
    b, entries = check_push(bundle_path, run_dir, trust, agents)
    return record_push(b, bundle_path, run_dir, entries, agents)


def check_push(bundle_path: Path, run_dir: Path, trust: tuple[Path, ...] = (), agents: list[int] | None = None):
    """Every check of a push, nothing written: (the bundle, the history)."""
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
    now = assignment(entries)
    fleet = is_fleet(run_dir)
    if fleet and agents is not None:
        raise BundleError(f"{run_dir}: a realtime fleet takes no staged rollout (--canary) yet: its world writes no "
                          "health.json for the gates; fix: push without --canary (each robot switches once it holds "
                          "the version; `hammer rollback` returns), or stage it on a lock-stepped `hammer serve` run")
    if fleet and served.wiring.has_central_network:
        check_central_pairing(b, _version_dir(run_dir, entries, now.base), now.base, fleet=True)
    if now.canary is not None:
        raise BundleError(f"{run_dir}: a staged rollout of version {now.canary} is open (agents "
                          f"{sorted(now.canary_agents)}); fix: wait for its decision, or `hammer rollback {run_dir}`")
    if agents is not None:
        bad = [i for i in agents if i >= served.n_agents]
        if bad or not agents:
            raise BundleError(f"--canary {','.join(map(str, agents))}: the run has agents 0..{served.n_agents - 1}; "
                              "fix: name at least one of them")
        if served.wiring.has_central_network:
            check_central_pairing(b, _version_dir(run_dir, entries, now.base), now.base)
    refuse_stopped(run_dir)  # last: what is wrong with the bundle itself is said first
    return b, entries


def _version_dir(run_dir: Path, entries: list[dict], version: int) -> Path:
    if version == 0:
        return Path(_served(run_dir)[0]["policy_dir"])
    return Path(next(e["policy_dir"] for e in entries if e["version"] == version))


def central_fingerprint(policy_dir: Path) -> str:
    """What a local policy is paired with: the sha256 of the central network's weights file."""
    return sha256(Path(policy_dir) / "central.safetensors")


def works_with(b) -> list[str]:
    """The central networks a bundle's local policy declares it works with: the manifest's
    `works_with_central` (fingerprints, `hammer export --works-with`), and always its own."""
    own = b.manifest["files"].get("central.safetensors")
    return [*([own] if own else []), *b.manifest.get("works_with_central", [])]


def check_central_pairing(b, served_dir: Path, version: int, fleet: bool = False) -> None:
    """A canary's local policy acts with the served central agent's messages (runtime/pushes.py):
    refuse a local policy that does not declare that central network. `fleet`: a realtime fleet's
    push, where each robot switches on its own, before or after the central agent does."""
    fp = central_fingerprint(served_dir)
    if fp not in works_with(b) and fleet:
        raise BundleError(f"{b.path}: its local policy does not declare the fleet's running central network "
                          f"(version {version}, sha256 {fp[:12]}); in a realtime fleet each robot switches on its "
                          "own, so robots on this local policy would act on that network's messages until the "
                          f"central agent switches; fix: export the bundle with `--works-with {served_dir}` if it "
                          "was trained against that central network, else restart the fleet with the new bundle")
    if fp not in works_with(b):
        raise BundleError(f"{b.path}: its local policy does not declare the served central network (version "
                          f"{version}, sha256 {fp[:12]}) and would be paired with it during the canary; fix: push "
                          "without --canary (every agent and the central agent switch together), or export the "
                          f"bundle with `--works-with {served_dir}` if it was trained against that central network")


def record_push(b, bundle_path: Path, run_dir: Path, entries: list[dict], agents: list[int] | None = None,
                extra: dict | None = None) -> dict:
    """Copy the bundle's policy into the run and append its entry (a canary: `agents` set)."""
    run_dir = Path(run_dir)
    version = max((e["version"] for e in entries), default=0) + 1
    dst = run_dir / POLICIES / f"v{version}"
    shutil.rmtree(dst, ignore_errors=True)
    dst.mkdir(parents=True)
    for name in b.manifest["files"]:
        shutil.copyfile(b.path / name, dst / name)
    entry = {"version": version, "action": "push", "policy_dir": str(dst.resolve()), "bundle": str(Path(bundle_path).resolve()),
             "files": {n: sha256(dst / n) for n in b.manifest["files"]}, "at": time.strftime("%Y-%m-%dT%H:%M:%S")}
    if agents is not None:
        entry.update(action="canary", agents=sorted(agents), base_version=assignment(entries).base)
    entry.update(extra or {})
    _write_history(run_dir, [*entries, entry])
    return entry


def effective_stack(run_dir: Path, entries: list[dict]) -> list[dict]:
    """The policies in effect, oldest first: the served one (version 0), each push on top, each rollback
    taking the top off."""
    rt, _ = _served(run_dir)
    stack = [{"version": 0, "policy_dir": rt["policy_dir"]}]
    for e in entries:
        if e.get("action") in ("stage", "promote", *RECORD_ONLY):  # a staged rollout's steps: same version
            continue
        if e.get("action") == "rollback":
            stack.pop()
            stack[-1] = {**stack[-1], "version": e["version"]}
        else:
            stack.append(e)
    return stack


def rollback(run_dir: Path, reason: dict | None = None) -> dict:
    """Return the served run to the policy in effect before its latest push (as a new version); an
    open canary ends with it (every agent back on the base). `reason`: kept in the entry."""
    run_dir = Path(run_dir)
    entries = read_history(run_dir)
    stack = effective_stack(run_dir, entries)
    if len(stack) < 2:
        raise BundleError(f"{run_dir}: nothing to roll back (the run serves its first policy); fix: `hammer push` first")
    back = stack[-2]
    version = max(e["version"] for e in entries) + 1
    entry = {"version": version, "action": "rollback", "policy_dir": back["policy_dir"],
             "restores_version": back["version"], "at": time.strftime("%Y-%m-%dT%H:%M:%S")}
    if "files" in back:
        entry["files"] = back["files"]
    entry.update(reason or {})
    _write_history(run_dir, [*entries, entry])
    return entry
