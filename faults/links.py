"""Per-link counters of a run, assembled from what each role counted.

No single process sees a whole link: the sender's fault layer knows what it dropped, duplicated or
delayed; the receiver knows what arrived on time, late (for a step it already acted on) or twice,
and what it did instead (a fallback message, a default action). Each role reports its own counters
(heartbeats while running, `counters/<role>-<pid>.json` at exit); `link_table` joins them into one
row per link:

    sent        messages the sender published (before faults)
    dropped     lost by the fault layer          duplicated  sent twice by the fault layer
    delayed     held back by delay/jitter/reorder
    delivered   copies the receiver got (on time + late + duplicate + stale)
    late        arrived for a step already acted on (never applied)
    duplicate   second copy of a step's message (never applied twice)
    fallbacks   central->local: agent x env-copy entries acted on a fallback message
    defaults    local->env: agent x env-copy entries that used the declared default action

A sender's counters of a process killed between two heartbeats lag behind what its receivers
counted; a row where `delivered` would exceed `sent` (plus the fault layer's copies) gets `sent`
raised to match and the difference in `unreported` (only on such rows), so the table stays
consistent and says why.

`degraded_reasons` is the end-of-run verdict: default actions or fallback messages above a
fraction of the agent x env-copy steps, or messages rejected by the roles (`rejected.<reason>`).

Imports stay light (no torch): the local-agent client uses `flat_fault_counters`.
"""

from __future__ import annotations

import json
from pathlib import Path

# The step loop's links and the keys (relative to hammer/<run>/) their messages travel on; the link
# fault specs (faults/spec.py) write rules for these. Here, not there, so a role that only counts
# (every local agent, the edge agent) loads no fault-spec models.
LINKS: dict[str, str] = {
    "env->central": "env/state",
    "env->local": "env/obs/{agent}",
    "central->local": "central/msg/{agent}",
    "local->env": "agent/act/{agent}",
}
LINK_IDS = {link: link.replace("->", "_") for link in LINKS}
_FAULT_FIELDS = ("matched", "sent", "dropped", "duplicated", "delayed", "reordered")
# Shown under every link table: why delivered can exceed sent, and why live figures may not add up.
COUNTERS_NOTE = ("delivered counts every copy a receiver got: duplicated copies included, so it can exceed sent - "
                 "dropped; while a run is live each role's counters come from its last heartbeat (up to ~1 s apart)")
COLUMNS = ("sent", "dropped", "duplicated", "delayed", "delivered", "late", "duplicate", "fallbacks", "defaults")


def link_of_pattern(match: str) -> str | None:
    """Which step-loop link a rule's key pattern belongs to (None: another or several)."""
    for link, pattern in LINKS.items():
        head = pattern.split("/{")[0]
        if match == head or match.startswith(head + "/"):
            return link
    return None


def flat_fault_counters(report: dict[str, dict[str, int]]) -> dict[str, int]:
    """A session's fault report ({'i:pattern': counters}) summed per link, as flat heartbeat
    counters named `fault.<link_id>.<field>` (rules on other keys go under `fault.other`)."""
    out: dict[str, int] = {}
    for label, counts in report.items():
        link = link_of_pattern(label.split(":", 1)[1])
        lid = LINK_IDS[link] if link else "other"
        for f in _FAULT_FIELDS:
            key = f"fault.{lid}.{f}"
            out[key] = out.get(key, 0) + int(counts.get(f, 0))
    return out


def write_role_counters(run_dir: Path, role: str, pid: int, counters: dict) -> None:
    """A role's final counters (own counters + its fault layer's), for `collect_role_counters`."""
    d = Path(run_dir) / "counters"
    d.mkdir(exist_ok=True)
    (d / f"{role}-{pid}.json").write_text(json.dumps({"role": role, "pid": pid, "counters": counters}))


def collect_role_counters(run_dir: Path, last_heartbeats: dict[tuple[str, int], dict]) -> dict[str, dict]:
    """Counters per role, summed over its process instances (a restarted role has several): the
    final file where the process wrote one, else its last heartbeat (a SIGKILLed process)."""
    per_pid: dict[tuple[str, int], dict] = dict(last_heartbeats)
    d = Path(run_dir) / "counters"
    if d.is_dir():
        for f in d.glob("*.json"):
            rec = json.loads(f.read_text())
            per_pid[(rec["role"], int(rec["pid"]))] = rec["counters"]
    roles: dict[str, dict] = {}
    for (role, _), counters in per_pid.items():
        acc = roles.setdefault(role, {})
        for k, v in counters.items():
            if isinstance(v, (int, float)) and k not in ("policy_version", "paper_metric_100", "step_p50_ms",
                                                         "step_p99_ms"):
                acc[k] = acc.get(k, 0) + v
    return roles


def _fault(c: dict, link: str, field: str) -> int:
    return int(c.get(f"fault.{LINK_IDS[link]}.{field}", 0))


def link_table(roles: dict[str, dict], n_agents: int, uses_central: bool) -> dict[str, dict[str, int]]:
    """One row of COLUMNS per link from per-role counters (see the module docstring)."""
    env = roles.get("env", {})
    central = roles.get("central", {})
    locals_ = [roles.get(f"local-{i}", {}) for i in range(n_agents)]

    def lsum(key: str) -> int:
        return int(sum(c.get(key, 0) for c in locals_))

    steps = int(env.get("step", 0))
    rows: dict[str, dict[str, int]] = {}
    if uses_central:
        rows["env->central"] = {"sent": steps, "delivered": int(central.get("steps", 0) + central.get("states_stale", 0)
                                                                + central.get("states_skipped", 0)
                                                                + central.get("states_no_policy", 0)),
                                "late": int(central.get("states_stale", 0) + central.get("states_skipped", 0))}
    rows["env->local"] = {"sent": steps * n_agents, "delivered": lsum("steps") + lsum("obs_stale"),
                          "late": lsum("obs_stale")}
    if uses_central:
        rows["central->local"] = {"sent": int(central.get("steps", 0)) * n_agents,
                                  "delivered": lsum("msgs_on_time") + lsum("msgs_late") + lsum("msgs_duplicate"),
                                  "late": lsum("msgs_late"), "duplicate": lsum("msgs_duplicate"),
                                  "fallbacks": lsum("fallback_copies")}
    rows["local->env"] = {"sent": lsum("steps"),
                          "delivered": int(env.get("actions_on_time", 0) + env.get("actions_late", 0)
                                           + env.get("actions_duplicate", 0)),
                          "late": int(env.get("actions_late", 0)), "duplicate": int(env.get("actions_duplicate", 0)),
                          "defaults": int(env.get("default_actions", 0))}
    sender = {"env->central": env, "env->local": env, "central->local": central}
    for link, row in rows.items():
        snd = sender.get(link)
        faults = [snd] if snd is not None else locals_
        for f in ("dropped", "duplicated", "delayed"):
            row[f] = int(sum(_fault(c, link, f) for c in faults))
        for col in COLUMNS:
            row.setdefault(col, 0)
        unreported = row["delivered"] - row["duplicated"] - row["sent"]
        rows[link] = {col: row[col] for col in COLUMNS}
        if unreported > 0:  # the sender died between heartbeats: its last count lags its receivers'
            rows[link]["sent"] += unreported
            rows[link]["unreported"] = unreported
    return rows


def rejections(roles: dict[str, dict]) -> dict[str, dict[str, int]]:
    """Messages each role rejected, by reason ({role: {reason: n}}; roles with none left out)."""
    out: dict[str, dict[str, int]] = {}
    for role, counters in sorted(roles.items()):
        got = {k.split(".", 1)[1]: int(v) for k, v in counters.items() if k.startswith("rejected.") and v}
        if got:
            out[role] = got
    return out


def degraded_reasons(roles: dict[str, dict], links: dict[str, dict[str, int]], agent_steps: int,
                     fraction: float, max_rejections: int) -> list[str]:
    """Why a run counts as degraded (empty: it does not). agent_steps: agent x env-copy entries
    of the session (vector steps x K x N)."""
    reasons = []
    defaults = links.get("local->env", {}).get("defaults", 0)
    fallbacks = links.get("central->local", {}).get("fallbacks", 0)
    for what, n in (("default actions", defaults), ("fallback messages", fallbacks)):
        if agent_steps and n > fraction * agent_steps:
            reasons.append(f"{what} {n:,} of {agent_steps:,} agent-steps ({n / agent_steps:.1%} > {fraction:.1%})")
    rejected = rejections(roles)
    total = sum(sum(r.values()) for r in rejected.values())
    if total > max_rejections:
        per = "; ".join(f"{role} " + ", ".join(f"{k} {v}" for k, v in sorted(r.items()))
                        for role, r in rejected.items())
        reasons.append(f"{total} messages rejected ({per})")
    return reasons
