"""Staged rollout with health gates: `hammer push BUNDLE --to RUN --canary AGENTS [--stages ...] [--gate ...]`.

The new version goes to a subset of the local agents first (the canary); the rest and the central
agent stay on the version in effect (the base: runtime/pushes.py explains why the central agent
cannot be split, and serve/push.py refuses a canary whose local policy does not declare the served
central network). Over a window of episodes the canary's health is compared with the rest's,
and the team's metric with the window before the push; the rollout then goes on to the next stage,
is promoted (every agent and the central agent on the new version at one step), or is rolled back
(a new version carrying the base's weights, `hammer rollback`'s entry). After the promotion one more
window checks the team's metric (there is no rest left to compare with) and can still roll back.

Who drives it: this command, which stays until the verdict and prints each decision. Why not the
launcher: a push is the operator's act on a running service, the same command that has always
pushed; it needs nothing from the launcher but two files in the run directory, which the served
run writes anyway (RUN/health.json by the env host, env_host/health.py; RUN/pushes.json read by the
policy server and the env host), so it works unchanged whether the agents are on loopback, in
other namespaces or on other machines, and it opens no Zenoh session (no keys, no access rules).
Ctrl-C (or SIGTERM) before the verdict rolls back to the base: a rollout is not done until it is
promoted and held, so an interrupted one leaves the run as it was before the push, recorded as
`rollback` with reason `interrupted`. A killed command (SIGKILL) leaves the last recorded stage
serving, shown on the dashboard; `hammer rollback RUN` ends it.

The gates (each a limit on canary minus rest over the same window, so the load on the machine
cancels out): default-action rate, fallback-message rate, mean action latency (ms from the
observations going out to the action arriving), rejected messages and crashes/leaves per agent,
and the team's metric (`metric`: paper_metric or team_return, higher is better) against the
window before the push, as a drop relative to it. A cooperative team has one reward, so the metric
cannot be split between the canary and the rest: it is compared over time. Every decision, with
each gate's canary and rest values and its limit, goes into RUN/pushes.json and the log.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from hammer.runtime.pushes import HEALTH, assignment
from hammer.serve.bundle import BundleError
from hammer.serve.gate_defaults import GATE_DEFAULTS as D
from hammer.serve.push import _served, append_entry, check_push, read_history, record_push, rollback
from pydantic import BaseModel, ConfigDict, Field, ValidationError

log = logging.getLogger("hammer.canary")
STALE_S = 30.0  # health.json older than this: the served run is not stepping (the env host writes it twice a second)


class CanaryError(ValueError):
    """A bad option or a run that cannot take a staged rollout; one line naming the fix."""


class Gate(BaseModel):
    """The limits of a staged rollout (`--gate NAME=VALUE,...`); defaults suit a cn3/mw3 team."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    window_episodes: int = Field(D["window_episodes"], ge=1, description="episodes per window (the baseline, each stage, the hold)")
    metric: str = Field(D["metric"], pattern="^(paper_metric|team_return)$")
    metric_drop: float = Field(D["metric_drop"], ge=0.0, description="largest drop of the team metric, relative to the "
                                                           "window before the push")
    metric_z: float = Field(D["metric_z"], ge=0.0, description="a drop also fails only if it exceeds this many standard "
                                                     "errors of the difference of the two windows' means")
    default_rate: float = Field(D["default_rate"], ge=0.0, le=1.0, description="canary minus rest: share of default actions")
    fallback_rate: float = Field(D["fallback_rate"], ge=0.0, le=1.0, description="canary minus rest: share acted on a fallback")
    latency_ms: float = Field(D["latency_ms"], ge=0.0, description="canary minus rest: mean action latency")
    rejected: float = Field(D["rejected"], ge=0.0, description="canary minus rest: rejected messages per agent")
    crashes: float = Field(D["crashes"], ge=0.0, description="canary minus rest: restarts + leaves per agent")
    timeout_s: float = Field(D["timeout_s"], gt=0.0, description="a window that does not fill in this time rolls back")


def parse_gate(items: list[str], window_episodes: int | None = None) -> Gate:
    fields: dict[str, str] = {}
    for item in ",".join(items).split(","):
        if not item.strip():
            continue
        name, eq, value = item.partition("=")
        if not eq:
            raise CanaryError(f"--gate {item!r}: expected NAME=VALUE; fix: e.g. --gate metric_drop=0.1 "
                              f"(names: {', '.join(Gate.model_fields)})")
        fields[name.strip()] = value.strip()
    if window_episodes is not None:
        fields["window_episodes"] = str(window_episodes)
    try:
        return Gate(**fields)
    except ValidationError as e:
        err = e.errors()[0]
        name = ".".join(map(str, err["loc"]))
        opt = "--window-episodes" if name == "window_episodes" else f"--gate {name}"
        known = "" if name in Gate.model_fields else f" (names: {', '.join(Gate.model_fields)})"
        raise CanaryError(f"{opt}={fields.get(name, '')!r}: {err['msg']}{known}; fix: set a valid value") from None


def parse_stages(text: str | None, canary: list[int], n_agents: int) -> list[list[int]]:
    """`1,50%,100%` -> the agents of each stage: the first k of (the canary's agents, then the rest
    by index). Counts or percentages of the team (rounded up); increasing; the last is the team."""
    order = [*canary, *(i for i in range(n_agents) if i not in canary)]
    if not text:
        counts = [len(canary), n_agents]
    else:
        counts = []
        for tok in text.split(","):
            tok = tok.strip()
            try:
                c = math.ceil(float(tok[:-1]) * n_agents / 100) if tok.endswith("%") else int(tok)
            except ValueError:
                raise CanaryError(f"--stages {text!r}: {tok!r} is not a count or a percentage; fix: e.g. "
                                  "--stages 1,50%,100%") from None
            counts.append(c)
    if counts[0] == n_agents:
        raise CanaryError(f"--canary {','.join(map(str, canary))}: the first stage is the whole team; fix: name a "
                          "subset (a plain `hammer push` switches everyone)")
    if any(c < 1 or c > n_agents for c in counts) or counts != sorted(set(counts)) or counts[-1] != n_agents:
        raise CanaryError(f"--stages {text or ''!r} -> agents per stage {counts}: must rise from 1 to the team "
                          f"({n_agents}); fix: e.g. --stages 1,50%,100%")
    if counts[0] < len(canary):
        raise CanaryError(f"--stages: the first stage has {counts[0]} agents, --canary names {len(canary)}; fix: "
                          "name fewer canary agents or start the stages with that many")
    return [sorted(order[:c]) for c in counts]


@dataclass
class Snapshot:
    """One read of RUN/health.json."""

    data: dict

    @property
    def episodes(self) -> int:
        return int(self.data["episodes"])

    def agent(self, i: int) -> dict:
        return self.data["agents"][i]


def read_health(run_dir: Path) -> Snapshot | None:
    try:
        data = json.loads((Path(run_dir) / HEALTH).read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None
    if not isinstance(data, dict) or not isinstance(data.get("agents"), list):
        return None
    return Snapshot(data)


def _team(a: Snapshot, b: Snapshot, key: str) -> tuple[float, float, int] | None:
    """(mean, variance, episodes) of the team metric `key` over the episodes finished between a and b."""
    n = b.episodes - a.episodes
    if n <= 0:
        return None
    mean = (b.data[key] - a.data[key]) / n
    sq = key.replace("_sum", "_sq_sum")
    var = max((b.data[sq] - a.data[sq]) / n - mean**2, 0.0) if sq in b.data and sq in a.data else 0.0
    return mean, var, n


def _group(a: Snapshot, b: Snapshot, agents: list[int]) -> dict[str, float]:
    d = {k: sum(b.agent(i)[k] - a.agent(i)[k] for i in agents)
         for k in ("actions", "copies", "defaults", "fallbacks", "latency_ms_sum", "rejected", "restarts", "leaves")}
    n = max(len(agents), 1)
    return {"default_rate": d["defaults"] / max(d["copies"], 1), "fallback_rate": d["fallbacks"] / max(d["copies"], 1),
            "latency_ms": d["latency_ms_sum"] / max(d["actions"], 1), "rejected": d["rejected"] / n,
            "crashes": (d["restarts"] + d["leaves"]) / n}


def judge(gate: Gate, before: tuple[float, float, int] | None, a: Snapshot, b: Snapshot, canary: list[int],
          rest: list[int]) -> dict:
    """Each gate's canary and rest values, limit and verdict over the window a..b. The metric fails
    when it dropped by more than `metric_drop` of the baseline and by more than `metric_z` standard
    errors: an episode's metric varies (cn3: a standard deviation near 30% of the mean), and a
    rollback on noise would take a good version away."""
    key = "metric_sum" if gate.metric == "paper_metric" else "return_sum"
    checks: dict[str, dict] = {}
    during = _team(a, b, key)
    if before is not None and during is not None:
        (mb, vb, nb), (md, vd, nd) = before, during
        drop = (mb - md) / max(abs(mb), 1e-9)
        se = math.sqrt(vb / nb + vd / nd)
        checks["metric_drop"] = {"canary": round(md, 4), "rest": round(mb, 4), "value": round(drop, 4),
                                 "stderr": round(se, 4), "limit": gate.metric_drop,
                                 "ok": drop <= gate.metric_drop or mb - md <= gate.metric_z * se}
    if rest:
        c, r = _group(a, b, canary), _group(a, b, rest)
        for name in ("default_rate", "fallback_rate", "latency_ms", "rejected", "crashes"):
            limit = getattr(gate, name)
            checks[name] = {"canary": round(c[name], 4), "rest": round(r[name], 4), "limit": limit,
                            "ok": c[name] - r[name] <= limit}
    return checks


def _failed(checks: dict) -> list[str]:
    return [f"{n}: canary {c['canary']} vs {'before' if n == 'metric_drop' else 'rest'} {c['rest']} (limit {c['limit']})"
            for n, c in checks.items() if not c["ok"]]


class Rollout:
    """One staged rollout, from the push to the verdict (`run`)."""

    def __init__(self, bundle: Path, run_dir: Path, canary: list[int], stages: str | None, gate: Gate,
                 trust: tuple[Path, ...] = (), say: Callable[[str], None] = print, poll_s: float = 0.2) -> None:
        from hammer.learning.config import build_config

        self.run_dir, self.gate, self.say, self.poll_s = Path(run_dir), gate, say, poll_s
        n = build_config(_served(self.run_dir)[1]).n_agents
        self.n = n
        bad = [i for i in canary if not 0 <= i < n]
        if bad or not canary or len(set(canary)) != len(canary):
            raise CanaryError(f"--canary {','.join(map(str, canary))}: name distinct agents of 0..{n - 1}; fix: "
                              "e.g. --canary 0")
        self.stages = parse_stages(stages, canary, n)
        self.bundle, self.trust = Path(bundle), trust
        self.b, _ = check_push(bundle, run_dir, trust, agents=self.stages[0])  # every check before anything is written
        h = read_health(self.run_dir)
        if h is None:
            raise CanaryError(f"{self.run_dir / HEALTH}: missing; fix: push to a running `hammer serve` (its env host "
                              "writes each agent's health there)")
        age = time.time() - float(h.data.get("time", 0))
        if age > STALE_S:
            raise CanaryError(f"{self.run_dir / HEALTH}: last written {age:.0f} s ago (the served run is not stepping); "
                              "fix: push to a running `hammer serve`")
        self.version: int | None = None
        self.verdict: str | None = None

    # ----- waiting on the run ------------------------------------------------------------------
    def _wait(self, until: Callable[[Snapshot], bool], what: str) -> Snapshot | None:
        deadline = time.monotonic() + self.gate.timeout_s
        while time.monotonic() < deadline:
            s = read_health(self.run_dir)
            if s is not None and until(s):
                return s
            time.sleep(self.poll_s)
        self.say(f"no {what} within {self.gate.timeout_s:.0f} s")
        return None

    def _window(self, start: Snapshot) -> Snapshot | None:
        w = self.gate.window_episodes
        return self._wait(lambda s: s.episodes >= start.episodes + w, f"{w} episodes")

    def _named(self, agents: list[int], central: int) -> Snapshot | None:
        """The first read where the env host names the new version for `agents` (and `central` for
        the central agent), then the first episodes after it (begun under the old assignment) skipped."""
        v = self.version
        s = self._wait(lambda s: all(s.agent(i)["version"] == v for i in agents)
                       and s.data["central_version"] == central, f"step naming version {v}")
        return None if s is None else self._wait(lambda x: x.episodes > s.episodes, "episode")

    # ----- the rollout -------------------------------------------------------------------------
    def run(self) -> str:
        """Push, judge stage by stage, promote or roll back; returns the verdict ("promoted" or
        "rolled back"). Ctrl-C before the verdict rolls back (module docstring)."""
        try:
            return self._run()
        except KeyboardInterrupt:
            if self.version is not None and self.verdict is None:
                self._rollback({"reason": "interrupted"}, "interrupted")
            raise

    def _run(self) -> str:
        g = self.gate
        start = read_health(self.run_dir)
        self.say(f"baseline: {g.window_episodes} episodes before the push")
        end = self._window(start) if start is not None else None
        if end is None:
            raise CanaryError(f"{self.run_dir}: the served run finished no {g.window_episodes} episodes in "
                              f"{g.timeout_s:.0f} s; fix: push to a running `hammer serve`, or lower --window-episodes")
        key = "metric_sum" if g.metric == "paper_metric" else "return_sum"
        before = _team(start, end, key)
        if before is None:
            raise CanaryError(f"{self.run_dir}: no episode finished before the push; fix: push to a running `hammer serve`")
        base = assignment(read_history(self.run_dir)).base
        self.say(f"baseline {g.metric} {before[0]:.4f} over {before[2]} episodes (version {base})")
        _, entries = check_push(self.bundle, self.run_dir, self.trust, agents=self.stages[0])  # the history now
        e = record_push(self.b, self.bundle, self.run_dir, entries, agents=self.stages[0],
                        extra={"stages": self.stages, "gate": g.model_dump(), "baseline": {g.metric: before[0], "episodes": before[2]}})
        self.version, policy_dir = e["version"], e["policy_dir"]
        self.say(f"version {self.version} on agents {self.stages[0]} (stage 1/{len(self.stages)}); the rest and the "
                 f"central agent stay on {base}")
        for k, agents in enumerate(self.stages):
            final = k == len(self.stages) - 1
            a = self._named(agents if not final else list(range(self.n)), base if not final else self.version)
            b = self._window(a) if a is not None else None
            if b is None:
                return self._rollback({"stage": k + 1, "reason": "no health", "agents": agents}, "timed out")
            rest = [i for i in range(self.n) if i not in agents]
            checks = judge(g, before, a, b, agents, rest)
            failed = _failed(checks)
            decision = {"stage": k + 1, "canary_agents": agents, "episodes": [a.episodes, b.episodes], "checks": checks}
            if failed:
                return self._rollback({**decision, "reason": "gate " + "; ".join(failed)}, "gate failed")
            if final:
                append_entry(self.run_dir, {"version": self.version, "action": "gate", "policy_dir": policy_dir,
                                            "passed": True, **decision, "at": _now()})
                self.verdict = "promoted"
                self.say(f"held: version {self.version} serves every agent ({_summary(checks)})")
                return self.verdict
            nxt = self.stages[k + 1]
            last = k + 1 == len(self.stages) - 1
            entry = {"version": self.version, "action": "promote" if last else "stage", "policy_dir": policy_dir,
                     **({} if last else {"agents": nxt}), "decision": decision, "at": _now()}
            append_entry(self.run_dir, entry)
            log.info("stage %d passed: %s", k + 1, _summary(checks))
            self.say(f"stage {k + 1} passed ({_summary(checks)}); "
                     + ("promoted: every agent and the central agent" if last else f"stage {k + 2}: agents {nxt}")
                     + f" on version {self.version}")
        raise AssertionError("unreachable")

    def _rollback(self, reason: dict, verdict: str) -> str:
        e = rollback(self.run_dir, {"reason": reason.pop("reason"), "decision": reason})
        self.verdict = "rolled back"
        self.say(f"rolled back ({verdict}): {e['reason']}; version {e['version']} serves the policy of version "
                 f"{e['restores_version']}")
        log.warning("rolled back version %s: %s", self.version, e["reason"])
        return self.verdict


def _summary(checks: dict) -> str:
    return ", ".join(f"{n} {c['canary']} vs {c['rest']}" for n, c in checks.items())


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S")


def staged_push(bundle: Path, run_dir: Path, canary: list[int], stages: str | None = None, gate: Gate | None = None,
                trust: tuple[Path, ...] = (), say: Callable[[str], None] = print) -> str:
    """The library form of `hammer push --canary`: returns "promoted" or "rolled back"."""
    try:
        return Rollout(bundle, run_dir, canary, stages, gate or Gate(), trust, say).run()
    except BundleError as e:
        raise CanaryError(str(e)) from None
