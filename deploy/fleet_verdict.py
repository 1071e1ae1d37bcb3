"""A fleet's verdict: whether the run was degraded, and why, in names an operator can act on.

Four kinds of reason, each naming the robot or the role it is about (docs/fleet.md, "The verdict"):

- a robot the world missed longer than `max_absence_s`, or never heard of at all (a robot that never
  joined is an absence for the whole run, not an empty line);
- a robot the central agent missed longer than `max_absence_s` (the world may have heard it all the
  while: the robot then acted on its fallback, blind to the team);
- payloads refused on a robot's own keys (`rejected_on`: too large, undecodable, another robot's
  index in the payload, a queue overflow): whoever sent them held that robot's key or is that robot
  misbehaving, which an operator must not read as a link failure; with the robot also missing, the
  reason says the flood came first;
- every other refusal by a role, by reason, and connections refused at the transport (TLS handshakes
  of strangers, a revoked identity: `refused_connections`, read from the roles' Zenoh logs);
- a team with a site feed (what no robot observes, docs/fleet.md "The site feed"): the feed never
  reached the central agent, or was silent longer than `max_absence_s` at a time (its columns were
  zeros in the central agent's state meanwhile: the silent rule).
"""

from __future__ import annotations


def central_absences(central_counters: dict, names: list[str]) -> dict[str, dict]:
    """The central agent's view of who was missing (its heartbeat's `local_<i>.absent_max_s` and
    `local_<i>.joined`): {robot: {longest_absence_s, never_joined}}."""
    out = {}
    for name in names:
        key = name.replace("-", "_")
        if f"{key}.absent_max_s" in central_counters:
            out[name] = {"longest_absence_s": float(central_counters[f"{key}.absent_max_s"]),
                         "never_joined": not central_counters.get(f"{key}.joined", 1)}
    return out


def _central_rejected_on(central_counters: dict) -> dict[str, dict[str, int]]:
    out: dict[str, dict[str, int]] = {}
    for k, v in central_counters.items():
        head, _, reason = k.partition(".rejected.")
        if reason and head.startswith("local_") and v:
            out.setdefault(head.replace("_", "-"), {})[reason] = int(v)
    return out


def _role_rejections(counters: dict) -> dict[str, int]:
    return {k.split(".", 1)[1]: int(v) for k, v in counters.items() if k.startswith("rejected.") and v}


def _fmt(reasons: dict[str, int]) -> str:
    return ", ".join(f"{r} {n:,}" for r, n in sorted(reasons.items(), key=lambda x: -x[1]))


def refused_connections(roles: dict[str, dict], launcher: dict[str, int]) -> dict[str, dict[str, int]]:
    """Per process that counts them (the launcher's hub, and the roles' `refused.<reason>` heartbeat
    counters), the connections Zenoh refused, by reason, with their `total`."""
    out = {role: {k.split(".", 1)[1]: int(v) for k, v in r.get("counters", {}).items() if k.startswith("refused.")}
           for role, r in roles.items()}
    out["launcher"] = dict(launcher)
    return {role: {**r, "total": sum(r.values())} for role, r in sorted(out.items()) if r}


def site_feed_view(central_counters: dict, world: dict) -> dict:
    """The site feed as summary.json's `site` shows it: what the central agent took of it (states,
    ticks on zeros, silences, longest silence, whether it ever came) and what the world published
    (in simulation)."""
    return {"states": int(central_counters.get("site_states", 0)),
            "silent_ticks": int(central_counters.get("site_silent_ticks", 0)),
            "silences": int(central_counters.get("site_silences", 0)),
            "longest_silence_s": float(central_counters.get("site.absent_max_s", 0.0)),
            "never_heard": not central_counters.get("site.joined", 1),
            "published_by_world": world.get("site_published"),
            # a site elsewhere in simulation: the ticks the world handed it (RUN/warehouse.npy)
            "recorded_by_world": world.get("site_recorded")}


def fleet_verdict(names: list[str], absences: dict[str, dict], world: dict, roles: dict[str, dict],
                  max_absence_s: float, launcher_refused: dict[str, int] | None = None,
                  site_feed: bool = False) -> dict:
    """{reasons, central_absences, rejections, rejected_on, refused_connections, site}: the degraded
    reasons (empty: not degraded) and what they were judged from, for summary.json. `roles`: each
    role's last heartbeat ({role: {"counters": ..., "gauges": ...}}); `world`: the world's report
    (world.json); `site_feed`: the team has one (its `site` view, else None)."""
    central_counters = roles.get("central", {}).get("counters", {})
    refused = refused_connections(roles, launcher_refused or {})
    reasons: list[str] = []
    rejected_on: dict[str, dict[str, dict[str, int]]] = {}
    for name, r in world.get("rejected_on", {}).items():
        rejected_on.setdefault(name, {})["env"] = r
    for name, r in _central_rejected_on(central_counters).items():
        rejected_on.setdefault(name, {})["central"] = r
    flooded = {name: sum(sum(r.values()) for r in by_role.values()) for name, by_role in rejected_on.items()}

    if names and all(absences.get(n, {}).get("never_joined") for n in names):
        reasons.append(f"no robot joined the fleet ({', '.join(names)} never heard of)")
    for name, a in absences.items():
        if name in flooded:
            continue  # named with its flood below
        if a.get("never_joined"):
            if len(names) > 1 and not all(absences.get(n, {}).get("never_joined") for n in names):
                reasons.append(f"{name} never joined (the world heard nothing from it in {a['longest_absence_s']:.1f} s)")
        elif a["longest_absence_s"] > max_absence_s:
            reasons.append(f"{name} was missing {a['longest_absence_s']:.1f} s at most (> max_absence_s "
                           f"{max_absence_s:g} s; {a['leaves']} time(s))")

    central = central_absences(central_counters, names)
    for name, c in central.items():
        if name in flooded or absences.get(name, {}).get("never_joined"):
            continue  # the world's reason already names it
        world_s = absences.get(name, {}).get("longest_absence_s", 0.0)
        if c["never_joined"]:
            reasons.append(f"the central agent never heard from {name} (the world did): it acted without the team's "
                           f"messages")
        elif c["longest_absence_s"] > max_absence_s and c["longest_absence_s"] > world_s + 1.0:
            reasons.append(f"the central agent lost {name} for {c['longest_absence_s']:.1f} s at most (> max_absence_s "
                           f"{max_absence_s:g} s) while the world missed it {world_s:.1f} s at most: its messages "
                           f"did not reach the team")

    for name, by_role in sorted(rejected_on.items()):
        what = "; ".join(f"{role}: {_fmt(r)}" for role, r in sorted(by_role.items()))
        a = absences.get(name)
        missing = "" if not a else (f"; {name} itself never joined" if a.get("never_joined") else
                                    f"; {name} was missing {a['longest_absence_s']:.1f} s at most")
        reasons.append(f"{flooded[name]:,} payloads refused on {name}'s own keys ({what}): sent by a holder of "
                       f"{name}'s key (stolen?) or a faulty {name}, not a link failure{missing}")

    site = site_feed_view(central_counters, world) if site_feed and "central" in roles else None
    if site is not None and site["never_heard"]:
        reasons.append("the site feed never reached the central agent: the columns no robot observes were zeros "
                       "in its state the whole run (silent rule)")
    elif site is not None and site["longest_silence_s"] > max_absence_s:
        reasons.append(f"the site feed was silent {site['longest_silence_s']:.1f} s at most (> max_absence_s "
                       f"{max_absence_s:g} s; {site['silences']} time(s)): the central agent's state had zeros for "
                       f"the columns no robot observes meanwhile (silent rule)")

    # every role's refusals (the world's from its report, which outlives its last heartbeat)
    rejections = {role: _role_rejections(r.get("counters", {})) for role, r in roles.items()}
    rejections["env"] = world.get("rejected") or rejections.get("env", {})
    rejections = {role: r for role, r in sorted(rejections.items()) if r}
    on_keys = {role: sum(r.get(role, {}).get(reason, 0) for r in rejected_on.values() for reason in r.get(role, {}))
               for role in ("env", "central")}
    other = {role: n for role, r in rejections.items() if (n := sum(r.values()) - on_keys.get(role, 0)) > 0}
    if other:
        reasons.append(f"{sum(other.values()):,} other payloads refused (" + "; ".join(
            f"{role}: {_fmt(rejections[role])}" for role in sorted(other)) + ")")
    for role, r in refused.items():
        reasons.append(f"{r['total']:,} connections refused by {role} (" + _fmt({k: v for k, v in r.items() if k != "total"})
                       + "): strangers or revoked identities tried to join, not a link failure")
    return {"reasons": reasons, "central_absences": central, "rejections": rejections, "rejected_on": rejected_on,
            "refused_connections": refused, "site": site}
