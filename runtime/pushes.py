"""Which policy version each agent of a served run acts with: the run's update history, read.

`hammer push` and `hammer rollback` (serve/push.py) and a staged rollout (serve/canary.py) write
RUN/pushes.json; the policy server publishes its versions and the env host names, per agent, the
version each step acts with. Both read the history here (runtime is below both: the env host may
not import serve/). Why per agent: a staged rollout gives the new local policy to a subset (the
canary) while the rest keep theirs; every LocalObs is per agent and carries a policy version, so
the env host can name two versions in one step with no new message field.

The central agent acts with one version per step (one GlobalState, one batched forward for every
agent), so during a canary it stays on the base version: the canary's local policy acts with the
central messages of the version before it. That pairing is only safe for a local policy trained
with (or declared compatible with) that central network; `serve.canary` refuses any other. At
full promotion the central agent switches to the new version at the same step as every agent.

Entries, oldest first (each has `version`, `policy_dir`, `action`):
  push      (no `agents`) every agent and the central agent switch to `version`
  rollback  likewise, to a version carrying older weights; ends any open canary
  canary    the agents in `agents` switch to `version`; the others and the central agent stay
  stage     the canary's agents become `agents` (same `version`: nothing new is published)
  promote   every agent and the central agent switch to the canary's `version` (nothing published)
  gate      a decision record only (a window passed); changes nothing
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

PUSHES = "pushes.json"
HEALTH = "health.json"
OPENS = ("canary", "stage")  # entries that leave a subset on a version of its own
RECORD_ONLY = ("gate",)  # entries that change no agent's version


class HistoryError(ValueError):
    """pushes.json cannot be read; the message names the file and the fix."""


def read_pushes(run_dir: Path) -> list[dict]:
    path = Path(run_dir) / PUSHES
    if not path.is_file():
        return []
    try:
        entries = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise HistoryError(f"{path}: not valid JSON ({e}); fix: restore it or remove it to serve the first policy")
    if not isinstance(entries, list) or not all(
            isinstance(e, dict) and isinstance(e.get("version"), int) and isinstance(e.get("policy_dir"), str)
            and (e.get("agents") is None or (isinstance(e["agents"], list)
                                             and all(isinstance(a, int) and a >= 0 for a in e["agents"])))
            for e in entries):
        raise HistoryError(f"{path}: expected a list of {{version, policy_dir, ...}} entries")
    return entries


@dataclass
class Assignment:
    """The versions in effect after some entries: `base` for the central agent and every agent
    outside the canary; `canary` for the agents in `canary_agents` (None: no canary open)."""

    base: int = 0
    canary: int | None = None
    canary_agents: frozenset[int] = frozenset()
    dirs: dict[int, str] = field(default_factory=dict)  # version -> policy_dir (version 0: not in the history)

    def version_of(self, agent: int) -> int:
        return self.canary if self.canary is not None and agent in self.canary_agents else self.base

    def agent_versions(self, n_agents: int) -> list[int]:
        return [self.version_of(i) for i in range(n_agents)]

    @property
    def newest(self) -> int:
        return self.base if self.canary is None else max(self.base, self.canary)


def assignment(entries: list[dict], published: int | None = None) -> Assignment:
    """The versions in effect after `entries`, taking them in order while their version is at most
    `published` (the newest version the caller has received: a version is named only once its
    weights are out, so no actor waits on a version still being read from disk)."""
    a = Assignment()
    for e in entries:
        v = e["version"]
        if published is not None and v > published:
            break
        action = e.get("action", "push")
        if action in RECORD_ONLY:
            continue
        a.dirs[v] = e["policy_dir"]
        if action in OPENS:
            a.canary, a.canary_agents = v, frozenset(e.get("agents") or ())
        else:  # push, rollback, promote: everyone on `v`
            a.base, a.canary, a.canary_agents = v, None, frozenset()
    return a
