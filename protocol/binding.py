"""Every message bound to the key it came on.

Zenoh's access rules (protocol/access.py) decide who may publish on a key; they cannot see inside
a payload. A message that names an agent, a role or a sender must therefore say exactly what its
key says, or a peer allowed on its own key could speak for another: a stolen `local-1` identity
publishing on `agent/act/1` an action whose `agent` is 0, or a heartbeat on `ctl/hb/local-1` whose
`role` is `env`. `check_key` is applied by every typed subscription to every message it delivers
(protocol/session.py), so no receiver can forget it; a mismatch is a `KeyMismatchError`, counted
under `rejected.key_mismatch` like any other bad message. A publisher stamps the sender its key
implies (`sender_of`), so code never has to repeat what the key says.

What each key says (keys under `hammer/<run>/`; `<pool>` is an agent pool `locals-<a>-<b>` or
`locals-<i>_<j>_...` that serves the agent):

| key | type | agent / role in the payload | sender |
|---|---|---|---|
| `env/obs/<i>` | local_obs | agent = i | env |
| `env/state` | global_state | | env |
| `central/msg/<i>` | central_msg | agent = i | central |
| `agent/act/<i>` | action | agent = i | local-i or its pool |
| `learn/team/exp` | experience | role = team | env |
| `learn/central/exp` | experience | role = central | central |
| `learn/<net>/weights` | weights | role = net | learner |
| `ctl/hb/<r>` | heartbeat | role = r | r (an agent: also its pool) |
| `ctl/all` | control | | any (a role obeys only the launcher's and the env host's stop) |

The run id needs no rule of its own: a subscription only covers its own run's prefix and `decode`
refuses a payload whose `run` differs. Keys outside this layout (`bench/...`) carry no identity.
"""

from __future__ import annotations

import re

from hammer.protocol.errors import KeyMismatchError

_POOL_RANGE = re.compile(r"^locals-(\d+)-(\d+)$")
_POOL_LIST = re.compile(r"^locals-(\d+(?:_\d+)*)$")

# Who publishes on each key family (a key's first two chunks), and which message type it carries.
_SENDER = {("env", "obs"): "env", ("env", "state"): "env", ("central", "msg"): "central"}
_TYPE = {("env", "obs"): "local_obs", ("env", "state"): "global_state", ("central", "msg"): "central_msg",
         ("agent", "act"): "action"}
_EXP_SENDER = {"team": "env", "central": "central"}


def sender_of(rel: str) -> str | None:
    """The sender a key implies (what a publisher stamps on it), or None where the key names none
    (`ctl/all`, `bench/...`): then the session's own name is stamped."""
    parts = rel.split("/")
    head = tuple(parts[:2])
    if head in _SENDER:
        return _SENDER[head]
    if head == ("agent", "act") and len(parts) == 3:
        return f"local-{parts[2]}"
    if parts[0] == "learn" and len(parts) == 3:
        return _EXP_SENDER.get(parts[1]) if parts[2] == "exp" else "learner" if parts[2] == "weights" else None
    if head == ("ctl", "hb") and len(parts) == 3:
        return parts[2]
    return None


def pool_agents(name: str) -> frozenset[int]:
    """The agents an agent pool's name covers (`locals-0-3`, `locals-0_2_5`); empty for another name."""
    if m := _POOL_RANGE.match(name):
        return frozenset(range(int(m[1]), int(m[2]) + 1))
    if m := _POOL_LIST.match(name):
        return frozenset(int(x) for x in m[1].split("_"))
    return frozenset()


def _agent_sender(sender: str, agent: int) -> bool:
    return sender == f"local-{agent}" or agent in pool_agents(sender)


def _mismatch(what: str, claimed: object, key: str) -> KeyMismatchError:
    return KeyMismatchError(f"payload says {claimed!r}, the key it came on ({key}) says otherwise", what)


def check_key(msg, rel: str) -> None:
    """Raise KeyMismatchError when `msg` claims an identity its key `rel` (relative to the run
    prefix, e.g. `agent/act/1`) does not give it. `msg` is a decoded protocol message."""
    parts = rel.split("/")
    head = tuple(parts[:2])
    tag = msg.type
    if head in _TYPE:
        if tag != _TYPE[head]:
            raise _mismatch("type", tag, rel)
        if len(parts) == 3:  # a per-agent key
            agent = _int(parts[2], rel)
            if msg.agent != agent:
                raise _mismatch("agent", msg.agent, rel)
            if head == ("agent", "act"):
                if not _agent_sender(msg.sender, agent):
                    raise _mismatch("sender", msg.sender, rel)
                return
        if msg.sender != _SENDER[head]:
            raise _mismatch("sender", msg.sender, rel)
        return
    if parts[0] == "learn" and len(parts) == 3:
        role, kind = parts[1], parts[2]
        want = {"exp": "experience", "weights": "weights"}.get(kind)
        if want is None:
            return
        if tag != want:
            raise _mismatch("type", tag, rel)
        if msg.role != role:
            raise _mismatch("role", msg.role, rel)
        sender = _EXP_SENDER.get(role) if kind == "exp" else "learner"
        if msg.sender != sender:
            raise _mismatch("sender", msg.sender, rel)
        return
    if head == ("ctl", "hb") and len(parts) == 3:
        role = parts[2]
        if tag != "heartbeat":
            raise _mismatch("type", tag, rel)
        if msg.role != role:
            raise _mismatch("role", msg.role, rel)
        agent = role.removeprefix("local-")
        if msg.sender != role and not (agent.isdigit() and int(agent) in pool_agents(msg.sender)):
            raise _mismatch("sender", msg.sender, rel)
        return
    if parts == ["ctl", "all"] and tag != "control":
        raise _mismatch("type", tag, rel)


def _int(chunk: str, rel: str) -> int:
    if not chunk.isdigit():
        raise KeyMismatchError(f"key {rel} does not name one agent", "agent")
    return int(chunk)
