"""Every message bound to the key it came on.

Zenoh's access rules (protocol/access.py) decide who may publish on a key; they cannot see inside
a payload. A message that names an agent, a role or a sender must therefore say exactly what its
key says, or a peer allowed on its own key could speak for another: a stolen `local-1` identity
publishing on `agent/act/1` an action whose `agent` is 0, or a heartbeat on `ctl/hb/local-1` whose
`role` is `env`. `check_key` is applied by every typed subscription to every message it delivers
(protocol/session.py), so no receiver can forget it; a mismatch is a `KeyMismatchError`, counted
under `rejected.key_mismatch` like any other bad message. A publisher stamps the sender its key
implies (`sender_of`) as an empty sender, which `check_key` fills in from the key: code never
has to repeat what the key says, and the wire does not carry it.

What each key says (keys under `hammer/<run>/`; `<pool>` is an agent pool `locals-<a>-<b>` or
`locals-<i>_<j>_...` that serves the agent):

| key | type | agent / role in the payload | sender |
|---|---|---|---|
| `env/obs/<i>` | local_obs | agent = i | env |
| `env/state` | global_state | | env |
| `site/state` | site_state | | site |
| `central/msg/<i>` | central_msg | agent = i | central |
| `agent/act/<i>` | action | agent = i | local-i or its pool |
| `agent/up/<i>` | uplink | agent = i | local-i or its pool |
| `learn/team/exp` | experience | role = team | env |
| `learn/central/exp` | experience | role = central | central |
| `learn/<net>/weights` | weights | role = net | learner |
| `learn/<net>/announce` | weights_announce | role = net | learner |
| `learn/<net>/chunk` | weights_chunk (a query's reply) | role = net | learner |
| `ctl/hb/<r>` | heartbeat | role = r | r (an agent: also its pool) |
| `ctl/all` | control | | any (a role obeys only the launcher's and the env host's stop) |

`learner` on the `learn/` keys is the name the key implies, whoever holds the weights: in a served
run its publisher is the policy server (identity `policy`, protocol/access.py), which sends the
sender empty as the learner does, so the bytes are the same and a receiver reads `learner`.

The run id needs no rule of its own: a subscription only covers its own run's prefix and `decode`
refuses a payload whose `run` differs. Keys outside this layout (`bench/...`) carry no identity.
"""

from __future__ import annotations

import functools
import re
from typing import NamedTuple

from hammer.protocol.errors import KeyMismatchError

_POOL_RANGE = re.compile(r"^locals-(\d+)-(\d+)$")
_POOL_LIST = re.compile(r"^locals-(\d+(?:_\d+)*)$")


class Rule(NamedTuple):
    """What a key says about the payloads on it (None: nothing, any is fine)."""

    type: str | None = None
    agent: int | None = None  # the payload's `agent`
    role: str | None = None  # the payload's `role`
    sender: str | None = None  # the sender a publisher stamps; also the only one accepted ...
    agent_pool: int | None = None  # ... or a pool serving this agent


def pool_agents(name: str) -> frozenset[int]:
    """The agents an agent pool's name covers (`locals-0-3`, `locals-0_2_5`); empty for another name."""
    if m := _POOL_RANGE.match(name):
        return frozenset(range(int(m[1]), int(m[2]) + 1))
    if m := _POOL_LIST.match(name):
        return frozenset(int(x) for x in m[1].split("_"))
    return frozenset()


@functools.lru_cache(maxsize=4096)
def rule_for(rel: str) -> Rule:
    """The rule of a key relative to its run's prefix (`agent/act/1`), parsed once per key: a
    subscription meets the same few keys every step."""
    parts = rel.split("/")
    head = tuple(parts[:2])
    if head in _AGENT_TYPES and len(parts) == 3:
        if not parts[2].isdigit():
            return Rule(type=_AGENT_TYPES[head], agent=-1)  # names no one agent: nothing may come on it
        i = int(parts[2])
        if head[0] == "agent":
            return Rule(_AGENT_TYPES[head], agent=i, sender=f"local-{i}", agent_pool=i)
        return Rule(_AGENT_TYPES[head], agent=i, sender=head[0] if head[0] == "central" else "env")
    if parts == ["env", "state"]:
        return Rule("global_state", sender="env")
    if parts == ["site", "state"]:
        return Rule("site_state", sender="site")
    if parts[0] == "learn" and len(parts) == 3 and parts[2] in _LEARN_TYPES:
        if parts[2] == "exp":
            return Rule("experience", role=parts[1], sender=_EXP_SENDER.get(parts[1], "env"))
        return Rule(_LEARN_TYPES[parts[2]], role=parts[1], sender="learner")
    if head == ("ctl", "hb") and len(parts) == 3:
        agent = parts[2].removeprefix("local-")
        return Rule("heartbeat", role=parts[2], sender=parts[2],
                    agent_pool=int(agent) if parts[2].startswith("local-") and agent.isdigit() else None)
    if parts == ["ctl", "all"]:
        return Rule("control")
    return Rule()  # bench/... and anything else: no identity


_AGENT_TYPES = {("env", "obs"): "local_obs", ("central", "msg"): "central_msg", ("agent", "act"): "action",
                ("agent", "up"): "uplink"}
_EXP_SENDER = {"team": "env", "central": "central"}
_LEARN_TYPES = {"exp": "experience", "weights": "weights", "announce": "weights_announce", "chunk": "weights_chunk"}


def sender_of(rel: str) -> str | None:
    """The sender a key implies (what a publisher stamps on it), or None where the key names none
    (`ctl/all`, `bench/...`): then the session's own name is stamped."""
    return rule_for(rel).sender


def _mismatch(what: str, claimed: object, key: str) -> KeyMismatchError:
    return KeyMismatchError(f"payload says {claimed!r}, the key it came on ({key}) says otherwise", what)


def check_key(msg, rel: str) -> None:
    """Raise KeyMismatchError when `msg` claims an identity its key `rel` (relative to the run
    prefix, e.g. `agent/act/1`) does not give it. `msg` is a decoded protocol message."""
    rule = rule_for(rel)
    if rule.type is not None and msg.type != rule.type:
        raise _mismatch("type", msg.type, rel)
    if rule.agent is not None and msg.agent != rule.agent:
        raise _mismatch("agent", msg.agent, rel)
    if rule.role is not None and msg.role != rule.role:
        raise _mismatch("role", msg.role, rel)
    if rule.sender is not None and not msg.sender:
        msg.sender = rule.sender  # sent empty: the sender its key implies (protocol.session stamps it so)
    elif rule.sender is not None and msg.sender != rule.sender and not (
            rule.agent_pool is not None and rule.agent_pool in pool_agents(msg.sender)):
        raise _mismatch("sender", msg.sender, rel)
