"""Who may publish and subscribe what: the role table and the Zenoh access rules built from it.

One table (`grants`) says, per role, which keys it may publish and which it may subscribe to;
everything else is denied. Zenoh enforces it through `access_control` with subjects matched by
the certificate common name of the other end of each link (protocol.identity), so every
process applies the same rules to everyone it talks to:

- ingress `put` from role R is accepted only on the keys R may publish (a forged action or
  weights message from a wrong identity never reaches the subscriber);
- egress `put` to role R is sent only on keys R may subscribe to (a role cannot read what it has
  no business reading by declaring a subscriber);
- R may declare subscribers only on its own subscriptions and a liveliness token only as itself;
- R may ask (a Zenoh query) only for keys it may subscribe to, gets replies only on those, and only
  a role that answers a key (the policy server, `policy`, for the weights) may declare a queryable
  on it or reply on it: a stolen agent key cannot answer a late joiner's request for the policy.

The weights come from `learner` in a training run and from `policy`, the policy server, in a served
run (`hammer serve`, a fleet): it learns nothing, and its identity may do less (no experience, no
liveliness watch). Both rows are in every run's table, so every process agrees on the rules whatever
it knows of the run (an edge agent joining with only its bundle); a run makes the identity of the one
it runs (`role_names`), and the key a publisher of weights stamps is the same for both
(protocol/binding.py).

Every process enforces the table on its own links, so the rules hold in both topologies:
peers meeting directly (`hammer up --secure`) and clients behind a router (`hammer hub --run-dir`,
where the router checks each hop and the clients accept what the router relays).

The router's identity (`hub`) exists only in a run made for a router (`router=True`, RuntimeSettings
`secure_hub`): whoever holds it may relay, and so originate, anything. A run whose roles meet as
peers has no `hub` identity and no relay rule, so no key of that run can speak for another role.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from hammer.protocol.identity import SITE_FEED, Identity
from hammer.protocol.keys import Keys

LAUNCHER = "launcher"
HUB = "hub"  # the `hammer hub` router of a secure multi-machine run: relays the run's traffic
SITE = SITE_FEED  # a fleet's site feed: what the central agent sees that no robot observes (docs/fleet.md)
LEARNER = "learner"  # the learner of a training run: experience in, weights out
POLICY = "policy"  # the policy server of a served run: a frozen (pushed, rolled back) policy out, learns nothing


def policy_role(served: bool) -> str:
    """The role that publishes the run's weights: the policy server in a served run (mode=eval), else
    the learner."""
    return POLICY if served else LEARNER


@dataclass(frozen=True)
class Grant:
    """Key expressions one role may publish and subscribe to (as declared, wildcards included)."""

    publish: tuple[str, ...] = ()
    subscribe: tuple[str, ...] = ()
    liveliness: tuple[str, ...] = ()  # tokens it may declare
    watch_liveliness: bool = False  # may subscribe to / query every role's liveliness
    relay: bool = False  # a router: forwards everyone's traffic (and checks each hop itself)
    answers: tuple[str, ...] = ()  # keys it answers queries on (a late joiner asks for the current policy)


Pools = tuple[tuple[str, tuple[int, ...]], ...]  # agent pools: (pool name, its agents)


def pool_name(agents: list[int]) -> str:
    """The pool's process name (logs, supervisor, secure identity): `locals-<first>-<last>`, with
    the full list when the agents are not one contiguous range."""
    if agents == list(range(agents[0], agents[-1] + 1)):
        return f"locals-{agents[0]}-{agents[-1]}"
    return "locals-" + "_".join(map(str, agents))


def role_names(n_agents: int, uses_central: bool = True, pools: Pools = (), router: bool = False,
               served: bool = False, site_feed: bool = False) -> list[str]:
    """Every identity a secure run creates: an agent pool has one identity of its own; `hub` only
    for a run whose roles meet through a router; the policy server's (`policy`) in a served run, the
    learner's in a training run; `site` only for a fleet whose team has a site feed."""
    return [LAUNCHER, "env", *(["central"] if uses_central else []), *(f"local-{i}" for i in range(n_agents)),
            *(name for name, _ in pools), policy_role(served), *([HUB] if router else []),
            *([SITE] if site_feed else [])]


def agent_weights(keys: Keys) -> tuple[str, ...]:
    """What a local agent receives of the policy: whole weights, a push's announcement, and the
    chunks it asks for (a query on `learn/local/chunk`, answered by the policy server)."""
    return keys.weights("local"), keys.weights_announce("local"), keys.weights_chunk("local")


def pool_grant(keys: Keys, name: str, agents: tuple[int, ...]) -> Grant:
    """An agent pool (one process serving several local agents, local_agent/pool.py) may do exactly
    what its agents may do, together: their keys, their heartbeats and liveliness tokens, and no
    other agent's."""
    return Grant(
        publish=(*(keys.act(i) for i in agents), *(keys.heartbeat(f"local-{i}") for i in agents)),
        subscribe=(*(keys.obs(i) for i in agents), *(keys.msg(i) for i in agents), *agent_weights(keys),
                   keys.ctl("all")),
        liveliness=tuple(keys.alive(f"local-{i}") for i in agents))


def grants(keys: Keys, n_agents: int, pools: Pools = (), router: bool = False) -> dict[str, Grant]:
    """The role table: what each role's job needs, nothing more (docs/security.md). `pools`: the
    run's agent pools, each granted exactly its agents' keys (`pool_grant`); `router`: the roles meet
    through a `hammer hub` router, which relays for everyone (and so is trusted with all)."""
    g = {
        # ctl/all: in a plain run the launcher hears the env host's end-of-budget stop (the roles that go
        # after it are stopping, not failing); a secure run's rules drop that stop, and the launcher stops all
        LAUNCHER: Grant(publish=(keys.ctl("all"),), subscribe=(keys.ctl("all"), keys.heartbeat("*")),
                        watch_liveliness=True),
        "env": Grant(
            publish=(keys.obs("*"), keys.state(), keys.exp("team"), keys.heartbeat("env")),
            # central/msg: a fleet's world puts each robot's central message into its observation
            subscribe=(keys.act("*"), keys.msg("*"), keys.weights("local"), keys.weights_announce("local"),
                       keys.ctl("all"), keys.heartbeat("*")),
            liveliness=(keys.alive("env"),)),
        "central": Grant(
            publish=(keys.msg("*"), keys.exp("central"), keys.heartbeat("central")),
            # the agents' heartbeats: a fleet's central agent switches to a pushed version once the
            # robots present hold it (their `policy_held`, central_agent/fleet_central.py)
            subscribe=(keys.state(), keys.up("*"), keys.site_state(), keys.weights("central"), keys.ctl("all"),
                       *(keys.heartbeat(f"local-{i}") for i in range(n_agents))),
            liveliness=(keys.alive("central"),)),
        # the site feed, and nothing else: no robot key may publish it, and the site reads nothing
        SITE: Grant(publish=(keys.site_state(),), liveliness=(keys.alive(SITE),)),
        LEARNER: Grant(
            publish=(keys.weights("local"), keys.weights("central"), keys.weights_announce("local"),
                     keys.heartbeat(LEARNER)),
            subscribe=(keys.exp("team"), keys.exp("central"), keys.ctl("all")),
            liveliness=(keys.alive(LEARNER),), watch_liveliness=True,
            answers=(keys.weights("local"), keys.weights("central"), keys.weights_chunk("local"))),
        # a served run's policy server: the weights out (each version once, a push announced and pulled in
        # chunks), a late joiner's query for them answered; no experience comes to it
        POLICY: Grant(
            publish=(keys.weights("local"), keys.weights("central"), keys.weights_announce("local"),
                     keys.heartbeat(POLICY)),
            subscribe=(keys.ctl("all"),),
            liveliness=(keys.alive(POLICY),),
            answers=(keys.weights("local"), keys.weights("central"), keys.weights_chunk("local"))),
    }
    if router:
        g[HUB] = Grant(relay=True)
    for i in range(n_agents):
        g[f"local-{i}"] = Grant(
            publish=(keys.act(i), keys.up(i), keys.heartbeat(f"local-{i}")),
            subscribe=(keys.obs(i), keys.msg(i), *agent_weights(keys), keys.ctl("all")),
            liveliness=(keys.alive(f"local-{i}"),))
    for name, agents in pools:
        g[name] = pool_grant(keys, name, agents)
    return g


def _rule(rid: str, flow: str, messages: list[str], key_exprs: tuple[str, ...] | list[str]) -> dict:
    return {"id": rid, "permission": "allow", "flows": [flow], "messages": messages, "key_exprs": list(key_exprs)}


def access_control(keys: Keys, n_agents: int, pools: Pools = (), router: bool = False) -> dict:
    """The `access_control` section every process of the run uses (default deny; relay rules for
    the `hub` identity only when the run uses a router)."""
    everything = [keys.all]
    rules: list[dict] = [
        # A process's own declarations may leave it; the receiving side decides what to accept.
        _rule("own-declarations", "egress", ["declare_subscriber", "liveliness_token", "declare_liveliness_subscriber",
                                              "liveliness_query", "declare_queryable", "query"], everything),
    ]
    subjects: list[dict] = []
    policies: list[dict] = [{"id": "own-declarations", "rules": ["own-declarations"], "subjects": []}]
    for role, g in grants(keys, n_agents, pools, router).items():
        subjects.append({"id": role, "cert_common_names": [role]})
        policies[0]["subjects"].append(role)
        mine = []
        if g.relay:
            mine.append(_rule(f"{role}-relays-in", "ingress", ["put", "declare_subscriber", "liveliness_token",
                                                               "declare_liveliness_subscriber", "liveliness_query",
                                                               "reply", "query", "declare_queryable"], everything))
            mine.append(_rule(f"{role}-relays-out", "egress", ["put", "reply"], everything))
        if g.publish:
            mine.append(_rule(f"{role}-publishes", "ingress", ["put"], g.publish))
        if g.subscribe:
            mine.append(_rule(f"{role}-receives", "egress", ["put", "reply"], g.subscribe))
            mine.append(_rule(f"{role}-subscribes", "ingress", ["declare_subscriber", "query"], g.subscribe))
        if g.answers:
            mine.append(_rule(f"{role}-answers-queries", "ingress", ["declare_queryable", "reply"], g.answers))
        if g.liveliness:
            mine.append(_rule(f"{role}-alive", "ingress", ["liveliness_token"], g.liveliness))
            mine.append(_rule(f"{role}-answers-liveliness", "ingress", ["reply"], g.liveliness))
        if g.watch_liveliness:
            mine.append(_rule(f"{role}-watches", "ingress", ["declare_liveliness_subscriber", "liveliness_query"],
                              [keys.alive("**")]))
            mine.append(_rule(f"{role}-liveliness-replies", "egress", ["reply"], [keys.alive("**")]))
        rules += mine
        policies.append({"id": f"{role}-policy", "rules": [r["id"] for r in mine], "subjects": [role]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


@dataclass(frozen=True)
class SecureLink:
    """What makes one process's Zenoh session secure: its TLS identity (mutual authentication, TLS
    links only) and the run's access rules."""

    identity: Identity
    access: dict = field(hash=False)

    def apply(self, cfg) -> None:
        """Write the TLS and access-control sections into a `zenoh.Config`."""
        missing = self.identity.missing()
        if missing:
            raise FileNotFoundError(f"identity of {self.identity.role!r} incomplete: {', '.join(map(str, missing))} "
                                    "missing (copy ca.pem, <role>.pem and <role>.key from the launcher's RUN/identity/)")
        tls = {
            "root_ca_certificate": str(self.identity.ca),
            "listen_certificate": str(self.identity.cert), "listen_private_key": str(self.identity.key),
            "connect_certificate": str(self.identity.cert), "connect_private_key": str(self.identity.key),
            "enable_mtls": True,
            # A role's address says nothing about who it is (peers meet at gossiped addresses on any
            # machine); its certificate's CN does, and the access rules check exactly that.
            "verify_name_on_connect": False,
        }
        cfg.insert_json5("transport/link/tls", json.dumps(tls))
        cfg.insert_json5("transport/link/protocols", json.dumps(["tls"]))
        cfg.insert_json5("access_control", json.dumps(self.access))


def secure_link(identity_directory: Path, role: str, keys: Keys, n_agents: int, pools: Pools = (),
                router: bool = False) -> SecureLink:
    from hammer.protocol.identity import identity_of

    return SecureLink(identity_of(identity_directory, role), access_control(keys, n_agents, pools, router))


def tls_endpoint(endpoint: str) -> str:
    """The TLS form of a tcp endpoint (secure runs listen and connect over TLS only)."""
    return "tls/" + endpoint.removeprefix("tcp/") if endpoint.startswith("tcp/") else endpoint
