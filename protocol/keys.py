"""Every Zenoh key expression hammer uses, built in one place.

All keys live under `hammer/<run>/`, so two runs on one host never see each other's traffic, and
names are validated here so a bad run id fails at startup with a clear message instead of
silently producing a wildcard or an empty key chunk.

  hammer/<run>/env/obs/<agent>          LocalObs to local agent <agent>
  hammer/<run>/env/state                GlobalState to the central agent
  hammer/<run>/central/msg/<agent>      CentralMsg to local agent <agent>
  hammer/<run>/agent/act/<agent>        Action from local agent <agent>
  hammer/<run>/site/state               SiteState from the site (what no robot observes) to a fleet's central agent
  hammer/<run>/learn/<role>/exp         ExperienceChunk to the learner: role "team" (env host's rollout),
                                        "central" (the central agent's per-step record)
  hammer/<run>/learn/<role>/weights     Weights from the learner (the policy server in a served run): role
                                        "local" or "central"
  hammer/<run>/learn/<role>/announce    WeightsAnnounce from the policy server: a pushed version to pull
  hammer/<run>/learn/<role>/chunk       WeightsChunk: the policy server's reply to `chunk?v=<version>&i=<index>`
  hammer/<run>/ctl/<name>               Control: "all" is the one every role listens to (stop, target
                                        "*" or a role name); ctl/<role> is reserved, nothing subscribes
  hammer/<run>/ctl/hb/<role>            Heartbeat of one role
  hammer/<run>/alive/<role>             liveliness token of one process
  hammer/<run>/bench/<name>             benchmark traffic

Role names: env, central, learner (a served run: policy, the policy server), local-<i>, site (a fleet's
site feed); the launcher sends as "launcher" and has no token.
docs/wire-format.md is this contract written for a client in another language.
"""

from __future__ import annotations

from dataclasses import dataclass

from hammer.protocol.fields import check_name

ROOT = "hammer"


def validate_run_id(run: str) -> str:
    """Return `run` if it is a safe key chunk, else raise ValueError saying what is allowed."""
    return check_name(run, "run id")


def _agent(agent: int | str) -> str:
    if isinstance(agent, bool) or not isinstance(agent, int | str):
        raise TypeError(f"agent must be an int index or '*', got {agent!r}")
    if isinstance(agent, int):
        if agent < 0:
            raise ValueError(f"agent index must be >= 0, got {agent}")
        return str(agent)
    if agent in ("*", "**"):
        return agent
    return check_name(agent, "agent")


def _name(name: str, what: str) -> str:
    if name in ("*", "**"):
        return name
    return check_name(name, what)


@dataclass(frozen=True)
class Keys:
    """Key expressions of one run. Agent/role arguments also accept '*' to build subscriptions."""

    run: str

    def __post_init__(self) -> None:
        validate_run_id(self.run)

    @property
    def prefix(self) -> str:
        return f"{ROOT}/{self.run}"

    @property
    def all(self) -> str:
        """Everything of this run."""
        return f"{self.prefix}/**"

    def obs(self, agent: int | str) -> str:
        return f"{self.prefix}/env/obs/{_agent(agent)}"

    def state(self) -> str:
        return f"{self.prefix}/env/state"

    def msg(self, agent: int | str) -> str:
        return f"{self.prefix}/central/msg/{_agent(agent)}"

    def act(self, agent: int | str) -> str:
        return f"{self.prefix}/agent/act/{_agent(agent)}"

    def up(self, agent: int | str) -> str:
        """A robot's uplink to the central agent in a fleet (its observation and last action)."""
        return f"{self.prefix}/agent/up/{_agent(agent)}"

    def site_state(self) -> str:
        """The site feed of a fleet: what the central agent sees that no robot observes (a warehouse
        management system's requested shelves and goals), from the site's own identity."""
        return f"{self.prefix}/site/state"

    def exp(self, role: str) -> str:
        return f"{self.prefix}/learn/{_name(role, 'role')}/exp"

    def weights(self, role: str) -> str:
        return f"{self.prefix}/learn/{_name(role, 'role')}/weights"

    def weights_announce(self, role: str) -> str:
        return f"{self.prefix}/learn/{_name(role, 'role')}/announce"

    def weights_chunk(self, role: str) -> str:
        return f"{self.prefix}/learn/{_name(role, 'role')}/chunk"

    def ctl(self, name: str = "all") -> str:
        """Control channel: `ctl("all")` for broadcast commands, `ctl(role)` for one role."""
        return f"{self.prefix}/ctl/{_name(name, 'control channel')}"

    def heartbeat(self, role: str) -> str:
        return f"{self.prefix}/ctl/hb/{_name(role, 'role')}"

    def alive(self, role: str) -> str:
        return f"{self.prefix}/alive/{_name(role, 'role')}"

    def bench(self, name: str) -> str:
        return f"{self.prefix}/bench/{_name(name, 'bench channel')}"

    def relative(self, key: str) -> str:
        """The part of `key` after `hammer/<run>/` (fault rules match on it); raises if not ours."""
        head = self.prefix + "/"
        if not key.startswith(head):
            raise ValueError(f"key {key!r} is not under this run's prefix {head!r}")
        return key[len(head):]

    def role_of_alive_key(self, key: str) -> str:
        """The role name of a liveliness key built by `alive(role)`."""
        return self.relative(key).removeprefix("alive/")

