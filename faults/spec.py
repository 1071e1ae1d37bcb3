"""Link / agent fault specs: what users write, turned into the protocol layer's FaultRules.

Users think in links of the step loop, not in Zenoh keys, so a fault is written per link with an
optional agent index:

    central->local:agent=1,drop=0.2,delay_ms=5,jitter_ms=2
    local->env:drop=0.05
    env->local:duplicate=0.1,reorder=0.2

Links and the keys (relative to hammer/<run>/) their messages travel on:

    env->central   env/state            the global state (hammer / random variants)
    env->local     env/obs/<i>          each local agent's observation
    central->local central/msg/<i>      each local agent's message
    local->env     agent/act/<i>        each local agent's action

Faults act on the publishing side (the `protocol.fault_injection` layer), seeded per (rule, key): the same
`--fault-seed` gives the same faults. Rules are ordered so that agent-specific rules win over
link-wide ones whatever order they were given in (the first matching rule applies to a key).
"""

from __future__ import annotations

from typing import Annotated, Any

import msgspec
from hammer.faults.links import LINKS
from hammer.protocol.fault_injection import FaultRule, FaultSpec, HoldMillis, Millis, Probability, Window
from hammer.protocol.structs import Meta, Settings, SettingsError, parse

PER_AGENT = {"env->local", "central->local", "local->env"}
_FIELDS = ("drop", "duplicate", "delay_ms", "jitter_ms", "reorder", "reorder_window", "reorder_max_hold_ms")


class FaultSpecError(ValueError):
    """A fault spec that cannot be parsed; the message names the part and the fix."""


class LinkFault(Settings):
    """Faults on one link of the step loop, for every agent or for one agent only."""

    link: str  # env->central | env->local | central->local | local->env
    agent: Annotated[int, Meta(ge=0)] | None = None  # only this local agent's key (None: every agent)
    drop: Probability = 0.0
    duplicate: Probability = 0.0
    delay_ms: Millis = 0.0
    jitter_ms: Millis = 0.0
    reorder: Probability = 0.0
    reorder_window: Window = 1
    reorder_max_hold_ms: HoldMillis = 100.0

    def check(self) -> None:
        if self.link not in LINKS:
            raise ValueError(f"link {self.link!r}: unknown; fix: use one of {', '.join(LINKS)}")
        if self.agent is not None and self.link not in PER_AGENT:
            raise ValueError(f"link {self.link}: has no per-agent keys; fix: drop 'agent='")

    @property
    def match(self) -> str:
        pattern = LINKS[self.link]
        return pattern.format(agent="*" if self.agent is None else self.agent)

    def rule(self) -> FaultRule:
        return FaultRule(match=self.match, **{f: getattr(self, f) for f in _FIELDS})

    def describe(self) -> str:
        who = f"agent {self.agent}" if self.agent is not None else "all agents" if self.link in PER_AGENT else ""
        parts = [f"drop {self.drop:.0%}"] if self.drop else []
        if self.delay_ms or self.jitter_ms:
            parts.append(f"delay {self.delay_ms:g} ms ± {self.jitter_ms:g} ms")
        if self.duplicate:
            parts.append(f"duplicate {self.duplicate:.0%}")
        if self.reorder:
            parts.append(f"reorder {self.reorder:.0%} (window {self.reorder_window})")
        return f"{self.link}{' (' + who + ')' if who else ''}: {', '.join(parts) or 'no faults'}"


class FaultPlan(Settings):
    """Every link fault of a run plus its seed (the YAML `faults:` section has this shape)."""

    seed: int = 0
    links: list[LinkFault] = msgspec.field(default_factory=list)

    def to_spec(self) -> FaultSpec | None:
        """The protocol-level spec; agent-specific rules first so they win over link-wide ones."""
        if not self.links:
            return None
        ordered = sorted(self.links, key=lambda lf: lf.agent is None)
        return FaultSpec(seed=self.seed, rules=[lf.rule() for lf in ordered])


def parse_link_fault(text: str) -> LinkFault:
    """`central->local:agent=1,drop=0.2,delay_ms=5` -> LinkFault (FaultSpecError on bad input)."""
    link, sep, rest = text.strip().partition(":")
    if not sep and "=" in link:
        raise FaultSpecError(f"--fault {text!r}: expected LINK:FIELD=VALUE,..., e.g. 'central->local:drop=0.2'")
    fields: dict[str, Any] = {"link": link.strip()}
    for item in filter(None, (p.strip() for p in rest.split(","))):
        key, eq, val = item.partition("=")
        if not eq:
            raise FaultSpecError(f"--fault {text!r}: {item!r} is not FIELD=VALUE (fields: agent, {', '.join(_FIELDS)})")
        key = key.strip()
        if key not in ("agent", *_FIELDS):
            raise FaultSpecError(f"--fault {text!r}: unknown field {key!r}; fix: use agent or one of {', '.join(_FIELDS)}")
        val = val.strip()
        if key.endswith("_ms") and val.endswith("ms"):
            val = val[:-2]
        if key in ("drop", "duplicate", "reorder") and val.endswith("%"):
            val = str(float(val[:-1]) / 100)
        fields[key] = val
    try:
        return parse(LinkFault, fields)
    except SettingsError as e:
        raise FaultSpecError(f"--fault {text!r}: {e.field or 'link'}: {e.msg}") from None


def build_plan(faults: list[str] | None = None, seed: int | None = None, section: Any = None) -> FaultPlan:
    """Merge a YAML `faults:` section (dict with seed/links, or a list of link dicts/strings) with
    `--fault` strings and `--fault-seed` (CLI wins for the seed, rules are added)."""
    plan = FaultPlan()
    if section is not None:
        if isinstance(section, list):
            section = {"links": section}
        if not isinstance(section, dict):
            raise FaultSpecError("faults: section must be a mapping {seed: N, links: [...]} or a list of link faults")
        links = [parse_link_fault(x) if isinstance(x, str) else x for x in section.get("links", [])]
        try:
            plan = parse(FaultPlan, {**section, "links": links})
        except SettingsError as e:
            raise FaultSpecError(f"faults.{e.field}: {e.msg}" if e.field else f"faults: {e.msg}") from None
    links = list(plan.links) + [parse_link_fault(f) for f in faults or []]
    return FaultPlan(seed=plan.seed if seed is None else seed, links=links)
