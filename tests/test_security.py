"""The secure profile over real Zenoh on 127.0.0.1: mutual TLS with per-run identities and the
access rules of protocol.access. Every forged message is published next to a legitimate one
sent after it on the same link, so "the legitimate one arrived, the forged one did not" is
decided without waiting on a timeout alone."""

from __future__ import annotations

import json
import stat
import time
from pathlib import Path

import msgspec
import pytest
from hammer.protocol.access import access_control, grants, role_names, secure_link
from hammer.protocol.identity import create_identities, identity_of
from hammer.protocol.keys import Keys
from hammer.protocol.session import HammerSession, TransportConfig, free_loopback_port

RUN = "sec1"
N = 2
KEYS = Keys(RUN)


def _tls(role: str, ident_dir: Path, listen: int | None = None, connect: int | None = None) -> TransportConfig:
    return TransportConfig(listen=[f"tls/127.0.0.1:{listen}"] if listen else ["tls/127.0.0.1:0"],
                           connect=[f"tls/127.0.0.1:{connect}"] if connect else [],
                           security=secure_link(ident_dir, role, KEYS, N))


@pytest.fixture(scope="module")
def idents(tmp_path_factory) -> Path:
    """A router run's identities (hub included); the peer team below uses the peer rules, which
    have no place for the hub's certificate."""
    d = tmp_path_factory.mktemp("identity")
    create_identities(d, [*role_names(N, router=True), "policy"])  # + a served run's policy server
    return d


@pytest.fixture(scope="module")
def other_ca(tmp_path_factory) -> Path:
    """Identities of the same role names signed by a different CA (a stranger's own PKI)."""
    d = tmp_path_factory.mktemp("other")
    create_identities(d, role_names(N), ca_name="stranger-ca")
    return d


@pytest.fixture(scope="module")
def team(idents):
    """env listens (the hub of this test); the other roles connect to it as peers."""
    port = free_loopback_port()
    opened = {"env": HammerSession(RUN, _tls("env", idents, listen=port), sender="env").open()}
    for role in ("launcher", "central", "local-0", "local-1", "learner", "policy"):
        opened[role] = HammerSession(RUN, _tls(role, idents, connect=port), sender=role).open()
    yield opened, port
    for s in opened.values():
        s.close()


def _settle() -> None:
    time.sleep(0.6)  # peers meet (gossip) and declarations propagate


def _wait_for(sub, n: int, timeout: float = 5.0) -> list[bytes]:
    got, deadline = [], time.monotonic() + timeout
    while len(got) < n and time.monotonic() < deadline:
        b = sub.get(0.05)
        if b is not None:
            got.append(b)
    return got


def _late_extra(sub, wait: float = 0.5) -> list[bytes]:
    time.sleep(wait)
    out = []
    while (b := sub.get(0)) is not None:
        out.append(b)
    return out


def test_identity_files_are_private_and_named_by_role(idents):
    assert stat.S_IMODE(idents.stat().st_mode) == 0o700
    for role in role_names(N, router=True):
        ident = identity_of(idents, role)
        for p in (ident.ca, ident.cert, ident.key):
            assert stat.S_IMODE(p.stat().st_mode) == 0o600, p
        from cryptography import x509

        cert = x509.load_pem_x509_certificate(ident.cert.read_bytes())
        assert cert.subject.rfc4514_string() == f"CN={role}"
    assert not list(idents.glob("ca*.key")), "the CA key is not kept"


def test_role_table_follows_the_issue():
    g = grants(KEYS, N)
    assert g["local-1"].publish == (KEYS.act(1), KEYS.up(1), KEYS.heartbeat("local-1"))  # up: a fleet robot's uplink
    assert KEYS.up("*") in g["central"].subscribe and not any(KEYS.up("*") in x.subscribe for r, x in g.items()
                                                              if r != "central")
    # a push's announcement and the chunks an agent asks for (a query on learn/local/chunk)
    assert set(g["local-1"].subscribe) == {KEYS.obs(1), KEYS.msg(1), KEYS.weights("local"), KEYS.ctl("all"),
                                           KEYS.weights_announce("local"), KEYS.weights_chunk("local")}
    publishers = {k: {r for r, x in g.items() if k in x.publish} for k in
                  (KEYS.msg("*"), KEYS.weights("local"), KEYS.weights("central"), KEYS.ctl("all"),
                   KEYS.weights_announce("local"))}
    # the weights come from the learner, or in a served run from the policy server (`policy`)
    assert publishers == {KEYS.msg("*"): {"central"}, KEYS.weights("local"): {"learner", "policy"},
                          KEYS.weights("central"): {"learner", "policy"}, KEYS.ctl("all"): {"launcher"},
                          KEYS.weights_announce("local"): {"learner", "policy"}}
    # only the policy server answers a chunk query: a stolen agent key cannot feed another agent's pull
    assert {r for r, x in g.items() if KEYS.weights_chunk("local") in x.answers} == {"learner", "policy"}
    # the policy server learns nothing: no experience comes to it
    assert not {KEYS.exp("team"), KEYS.exp("central")} & set(g["policy"].subscribe)
    # a run makes the identity of the one it runs
    assert "policy" in role_names(N, served=True) and "learner" not in role_names(N, served=True)
    assert "learner" in role_names(N) and "policy" not in role_names(N)
    acl = access_control(KEYS, N)
    assert acl["default_permission"] == "deny" and acl["enabled"] is True
    # no router, no relay: a run whose roles meet as peers has no hub identity and no rule for one
    assert "hub" not in role_names(N) and "hub" not in g
    assert not any("hub" in r["id"] for r in acl["rules"]) and "hub" not in {s["id"] for s in acl["subjects"]}
    assert "hub" in grants(KEYS, N, router=True) and grants(KEYS, N, router=True)["hub"].relay


def test_legitimate_traffic_flows(team):
    s, _ = team
    acts = s["env"].subscribe_raw(KEYS.act("*"))
    obs0 = s["local-0"].subscribe_raw(KEYS.obs(0))
    w0 = s["local-0"].subscribe_raw(KEYS.weights("local"))
    ctl = s["env"].subscribe_raw(KEYS.ctl("all"))
    msgs = s["local-1"].subscribe_raw(KEYS.msg(1))
    hb = s["launcher"].subscribe_raw(KEYS.heartbeat("*"))
    _settle()
    s["local-0"].put_bytes(KEYS.act(0), b"a0")
    s["local-1"].put_bytes(KEYS.act(1), b"a1")
    s["env"].put_bytes(KEYS.obs(0), b"o0")
    s["learner"].put_bytes(KEYS.weights("local"), b"w")
    s["launcher"].put_bytes(KEYS.ctl("all"), b"stop")
    s["central"].put_bytes(KEYS.msg(1), b"m1")
    s["local-1"].put_bytes(KEYS.heartbeat("local-1"), b"hb")
    assert sorted(_wait_for(acts, 2)) == [b"a0", b"a1"]
    assert _wait_for(obs0, 1) == [b"o0"]
    assert _wait_for(w0, 1) == [b"w"]
    assert _wait_for(ctl, 1) == [b"stop"]
    assert _wait_for(msgs, 1) == [b"m1"]
    assert _wait_for(hb, 1) == [b"hb"]


def test_liveliness_tokens_reach_the_launcher(team):
    s, _ = team
    watch = s["launcher"].watch_alive()
    s["local-0"].declare_alive("local-0")
    s["local-1"].declare_alive("local-0")  # impersonated token: refused
    deadline, seen = time.monotonic() + 5.0, set()
    while "local-0" not in seen and time.monotonic() < deadline:
        ev = watch.get(0.05)
        if ev is not None and ev.alive:
            seen.add(ev.role)
    assert "local-0" in seen


def test_local_agent_cannot_act_for_another(team):
    s, _ = team
    acts = s["env"].subscribe_raw(KEYS.act(0))
    _settle()
    for _ in range(20):
        s["local-1"].put_bytes(KEYS.act(0), b"forged")
    s["local-0"].put_bytes(KEYS.act(0), b"real")
    assert _wait_for(acts, 1) == [b"real"]
    assert _late_extra(acts) == []


def test_only_the_learner_publishes_weights(team):
    s, _ = team
    w_local = s["local-0"].subscribe_raw(KEYS.weights("local"))
    w_env = s["env"].subscribe_raw(KEYS.weights("local"))
    w_central = s["central"].subscribe_raw(KEYS.weights("central"))
    _settle()
    # A session's own subscribers get its own publications (that is no attack), so each forger
    # publishes only weights it does not itself subscribe to.
    for forger, network in (("local-1", "central"), ("central", "local"), ("env", "central"),
                            ("launcher", "local"), ("launcher", "central")):
        s[forger].put_bytes(KEYS.weights(network), b"forged")
    s["learner"].put_bytes(KEYS.weights("local"), b"real")
    s["learner"].put_bytes(KEYS.weights("central"), b"real")
    for sub in (w_local, w_env, w_central):
        assert _wait_for(sub, 1) == [b"real"]
        assert _late_extra(sub, 0.2) == []


def test_only_the_learner_answers_a_request_for_the_weights(team):
    """A late joiner asks for the current policy (a query, runtime/weights.py). A thief with local-1's
    key that answers such requests with its own well-formed weights reaches nobody; the learner's
    answer arrives; and local-0 cannot ask for the central agent's weights."""
    from hammer.protocol.codec import decode
    from hammer.protocol.schemas import Weights

    s, _ = team
    s["local-1"].answer(KEYS.weights("local"), lambda: Weights.from_blob("local", 99, b"forged"))
    ask_local = s["local-0"].subscribe_raw(KEYS.weights("local"))
    ask_central = s["local-0"].subscribe_raw(KEYS.weights("central"))
    _settle()
    s["local-0"].fetch(KEYS.weights("local"), ask_local, timeout=1.0)
    assert _late_extra(ask_local, 1.2) == []  # the thief's queryable and replies are refused
    s["learner"].answer(KEYS.weights("local"), lambda: Weights.from_blob("local", 3, b"real"))
    s["learner"].answer(KEYS.weights("central"), lambda: Weights.from_blob("central", 3, b"real"))
    _settle()
    s["local-0"].fetch(KEYS.weights("local"), ask_local, timeout=1.0)
    got = _wait_for(ask_local, 1)
    assert [decode(b, Weights).version for b in got] == [3]  # the learner's, not the thief's 99
    assert _late_extra(ask_local, 0.5) == []
    s["local-0"].fetch(KEYS.weights("central"), ask_central, timeout=1.0)
    assert _late_extra(ask_central, 1.2) == []  # not a key local-0 may read


def test_a_served_runs_policy_server_publishes_and_answers_the_weights_and_reads_no_experience(team):
    """The policy server (`policy`, a served run's) does what the learner does for the agents, and
    no more: its weights arrive, its answer to a late joiner arrives, the team's experience does not."""
    from hammer.protocol.codec import decode
    from hammer.protocol.schemas import Weights

    s, _ = team
    w_local = s["local-0"].subscribe_raw(KEYS.weights("local"))
    spy_exp = s["policy"].subscribe_raw(KEYS.exp("team"))
    _settle()
    s["policy"].put_bytes(KEYS.weights("local"), b"served")
    s["env"].put_bytes(KEYS.exp("team"), b"x")
    assert _wait_for(w_local, 1) == [b"served"]
    assert _late_extra(spy_exp, 0.3) == []
    ask = s["local-0"].subscribe_raw(KEYS.weights("local"))
    s["policy"].answer(KEYS.weights("local"), lambda: Weights.from_blob("local", 5, b"served"))
    _settle()
    # asked again each second as an agent does (a loaded machine may take longer to carry the
    # declaration); the learner of this module's team may answer too, when an earlier test declared
    # its answer, and the thief's (local-1's, an earlier test) never arrives
    versions, deadline = [], time.monotonic() + 10.0
    while 5 not in versions and time.monotonic() < deadline:
        s["local-0"].fetch(KEYS.weights("local"), ask, timeout=1.0)
        versions += [decode(b, Weights).version for b in _wait_for(ask, 1, timeout=1.0)]
    assert 5 in versions and 99 not in versions, versions


def test_only_the_launcher_publishes_control(team):
    """The env host too: in a plain run its end-of-budget stop is obeyed, here the rules drop it."""
    s, _ = team
    subs = {r: s[r].subscribe_raw(KEYS.ctl("all")) for r in ("env", "local-0", "central")}
    _settle()
    forgers = ("local-1", "central", "learner", "env")
    for forger in forgers:
        s[forger].put_bytes(KEYS.ctl("all"), f"forged-stop-{forger}".encode())
    s["launcher"].put_bytes(KEYS.ctl("all"), b"real")
    for role, sub in subs.items():
        got = _wait_for(sub, 2 if role in forgers else 1) + _late_extra(sub, 0.2)
        # a session's own subscribers see its own publications (Zenoh delivers them locally)
        own = [f"forged-stop-{role}".encode()] if role in forgers else []
        assert sorted(got) == sorted([b"real", *own]), role


def test_a_hub_certificate_is_worth_nothing_in_a_run_without_a_router(team, idents):
    """The same CA signed a `hub` certificate (a router run's identity), but the peer team's rules
    have no subject for it: it joins over mutual TLS and can neither act, publish weights, stop
    the run nor read anything."""
    _, port = team
    _probe_stranger(team, _tls("hub", idents, connect=port), also_forge=True)


def test_a_role_cannot_read_another_roles_inputs(team):
    s, _ = team
    spy_obs = s["local-1"].subscribe_raw(KEYS.obs(0))
    spy_msg = s["local-1"].subscribe_raw(KEYS.msg(0))
    spy_exp = s["local-1"].subscribe_raw(KEYS.exp("team"))
    real = s["local-0"].subscribe_raw(KEYS.obs(0))
    _settle()
    s["env"].put_bytes(KEYS.obs(0), b"o0")
    s["central"].put_bytes(KEYS.msg(0), b"m0")
    s["env"].put_bytes(KEYS.exp("team"), b"x")
    assert _wait_for(real, 1) == [b"o0"]
    for spy in (spy_obs, spy_msg, spy_exp):
        assert _late_extra(spy, 0.2) == []


def _probe_stranger(team, transport: TransportConfig, also_forge: bool = False) -> None:
    """A stranger on the env host's port can neither inject an action nor read an observation
    (also_forge: nor publish weights or control)."""
    s, _ = team
    acts = s["env"].subscribe_raw(KEYS.act(0))
    weights = s["local-0"].subscribe_raw(KEYS.weights("local"))
    ctl = s["local-0"].subscribe_raw(KEYS.ctl("all"))
    with HammerSession(RUN, transport, sender="stranger") as x:
        spy = x.subscribe_raw(KEYS.obs(0))
        _settle()
        for _ in range(20):
            x.put_bytes(KEYS.act(0), b"stranger")
            if also_forge:
                x.put_bytes(KEYS.weights("local"), b"stranger")
                x.put_bytes(KEYS.ctl("all"), b"stranger")
        s["env"].put_bytes(KEYS.obs(0), b"o0")
        s["local-0"].put_bytes(KEYS.act(0), b"real")
        s["learner"].put_bytes(KEYS.weights("local"), b"real")
        s["launcher"].put_bytes(KEYS.ctl("all"), b"real")
        assert _wait_for(acts, 1) == [b"real"]
        assert _wait_for(weights, 1) == [b"real"] and _wait_for(ctl, 1) == [b"real"]
        assert _late_extra(acts) == [] and _late_extra(weights, 0.1) == [] and _late_extra(ctl, 0.1) == []
        assert _late_extra(spy, 0.1) == []


def test_stranger_without_credentials_is_refused(team):
    _, port = team
    _probe_stranger(team, TransportConfig(connect=[f"tcp/127.0.0.1:{port}"]))


def test_stranger_over_tls_without_a_certificate_is_refused(team, idents):
    _, port = team
    link = secure_link(idents, "local-0", KEYS, N)
    bare = TransportConfig(connect=[f"tls/127.0.0.1:{port}"])
    cfg_ca = {"root_ca_certificate": str(link.identity.ca), "verify_name_on_connect": False}

    class NoCert(TransportConfig):
        def to_zenoh(self):
            import json

            cfg = super().to_zenoh()
            cfg.insert_json5("transport/link/tls", json.dumps(cfg_ca))
            return cfg

    _probe_stranger(team, NoCert(**msgspec.structs.asdict(bare)))


def test_certificate_from_another_ca_is_refused(team, other_ca):
    _, port = team
    _probe_stranger(team, _tls("local-0", other_ca, connect=port))


# --------------------------------------------------------------------------------------------
# End to end: a secure `hammer up` run with a hostile peer holding local-1's identity
# --------------------------------------------------------------------------------------------


def _metrics_without_wall_time(run_dir: Path) -> list[dict[str, str]]:
    import csv

    with open(run_dir / "metrics.csv", newline="") as f:
        return [{k: v for k, v in r.items() if k != "wall_time"} for r in csv.DictReader(f)]


def _weight_templates(cfg) -> dict[str, bytes]:
    """Blobs of the run's own architecture: what an attacker who read the public code can build."""
    from hammer.learner.worker import weights_blob
    from hammer.learning.run_env import make_env
    from hammer.learning.team import Team

    env = make_env(cfg)
    team = Team(cfg, env.spec)
    env.close()
    return {"local": weights_blob(team.local.export_numpy()), "central": weights_blob(team.central.export_numpy())}


def _hostile_peer(cfg):
    from tests.hostile_peer import HostilePeer

    templates = _weight_templates(cfg)
    return lambda stolen, run_id: HostilePeer(run_id, stolen, cfg.num_envs, agent=0, templates=templates,
                                              msg_dim=cfg.wiring.msg_dim)


def _secure_run(run_dir: Path, run_id: str, hostile: list | None = None, secure: bool = True, peer=_hostile_peer):
    """A `hammer up --secure` cn3 run; with `hostile` (a list), `peer(cfg)(transport, run_id)` joins it
    with local-1's identity once the run is up and is appended to the list. `peer(cfg)` prepares
    before the run starts, so that the peer joins on the launcher's first tick, before step 0 is far behind."""
    from hammer.deploy.launcher import launch
    from hammer.learning.config import merge_config
    from hammer.runtime.settings import RuntimeSettings

    cfg = merge_config("cn3", overrides=["episodes=100", "variant=hammer"])
    # Generous deadlines: the comparison is about forged traffic, so a loaded host must not turn a
    # slow message into a fallback.
    settings = RuntimeSettings(run_id=run_id, secure=secure, msg_deadline_ms=5000, act_deadline_ms=10000)

    make = peer(cfg) if hostile is not None else None

    def chaos(sup, board) -> None:
        if hostile is not None and not hostile:
            rt = RuntimeSettings.load(run_dir)
            stolen = rt.secured(TransportConfig(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{rt.hub_port}"]),
                                "local-1", run_dir, cfg.n_agents)
            p = make(stolen, rt.run_id)
            p.start()
            hostile.append(p)

    try:
        return launch(cfg, settings, run_dir, chaos=chaos)
    finally:
        for p in hostile or []:
            p.stop_event.set()
            p.join(10)


@pytest.fixture(scope="module")
def calm(tmp_path_factory) -> Path:
    """The run nobody attacks, what an attacked run must reproduce exactly: the session's `hammer up`
    of the same config with the same deadlines (runtime_helpers.up_run, test_runtime_up's rl run).
    It is a plain run: the secure profile changes the transport and its access rules, not one value
    of the run, so a secure run nobody attacks is this run too."""
    from tests.runtime_helpers import up_cn3, up_run

    calm = up_run(tmp_path_factory.mktemp("calm") / "calm", up_cn3("rl"))
    assert json.loads((calm / "summary.json").read_text())["completed"]
    return calm


def test_secure_run_is_unmoved_by_a_hostile_peer_with_a_stolen_identity(tmp_path, calm):
    hostile: list = []
    attacked = _secure_run(tmp_path / "attacked", "sec-attacked", hostile)
    peer = hostile[0]
    assert peer.error is None, peer.error
    t0 = peer.timeline["started"]
    assert peer.max_peers >= 2, ("the hostile peer never joined the run: the test would prove nothing",
                                 {k: round(t - t0, 2) for k, t in peer.timeline.items()})
    assert peer.sent["blind_actions"] > 0 and peer.sent["control"] > 0
    # it forged weights for both networks, inside every bound: the next version once it had read the
    # real local weights (local-1 may: test_legitimate_traffic_flows), a guess among the first 20 before.
    # (Whether it caught a publication is timing on a loaded host, so it is not asserted.)
    assert peer.sent["weights"] > 0
    assert peer.obs_seen == 0, "local-1's identity read agent 0's observations"
    assert attacked.summary["completed"]
    a, b = _metrics_without_wall_time(calm), _metrics_without_wall_time(tmp_path / "attacked")
    assert len(a) == 100 and a == b
    links = attacked.summary["links"]
    assert links["default_actions"] == 0 and links["off_policy_actions"] == 0
    # nothing reached a role for its own checks to refuse: only the access rules stood in the way
    assert attacked.summary["rejected"] == {} and attacked.summary["degraded"] is False


def _thief(cfg):
    from tests.own_key_thief import OwnKeyThief

    return lambda stolen, run_id: OwnKeyThief(run_id, stolen, agent=1)


def test_a_stolen_agent_key_is_that_agent_and_nothing_more(tmp_path, calm):
    """What a hostile peer with local-1's real identity files would try through local-1's
    own keys: act for agents 0 and 2, file heartbeats under `env`, negative and falling counters, a
    4 MB flood. None takes effect; each is counted and named in summary.json; the run completes with
    exactly the calm run's metrics."""
    hostile: list = []
    run = tmp_path / "thief"
    attacked = _secure_run(run, "sec-thief", hostile, peer=_thief)
    thief = hostile[0]
    assert thief.error is None, thief.error
    assert thief.obs_seen > 0, "the thief never read agent 1's observations: it was not in the run"
    assert all(n > 0 for n in thief.sent.values()), thief.sent
    assert attacked.summary["completed"] and attacked.summary["episodes"] == 100
    assert _metrics_without_wall_time(calm) == _metrics_without_wall_time(run)
    rejected = attacked.summary["rejected"]
    # the env host: actions naming agents 0 and 2 (or sender local-0) on agent 1's key; the flood,
    # refused on arrival by its size (an action of this run weighs at most a few kB)
    assert rejected["env"]["key_mismatch"] >= thief.sent["other_agent_actions"] // 2, rejected
    assert rejected["env"]["size"] > 0, rejected
    # the launcher: a heartbeat on local-1's key filed as env; negative counters; pids it never started
    assert {"key_mismatch", "field", "heartbeat_pid"} <= rejected["launcher"].keys(), rejected
    assert attacked.summary["degraded"] is True
    assert any("key_mismatch" in r and "launcher" in r for r in attacked.summary["degraded_reasons"])
    links = json.loads((run / "links.json").read_text())
    env = links["roles"]["env"]
    assert env.get("actions_duplicate", 0) == 0 and env.get("default_actions", 0) == 0  # the real agent 1 counted
    assert env["step"] < 10**6 and links["roles"]["local-1"]["steps"] < 10**6  # no forged figure was summed


def test_the_same_peer_ends_a_plain_run_early(tmp_path):
    """The plain profile trusts the sender header: the forged `stop` of `launcher` is obeyed."""
    from hammer.deploy.launcher import UpError

    hostile: list = []
    with pytest.raises(UpError, match="env host stopped before the budget"):
        _secure_run(tmp_path / "plain", "plain-attacked", hostile, secure=False)
    assert hostile and hostile[0].error is None and hostile[0].sent["control"] > 0
    env_log = (tmp_path / "plain" / "logs" / "env.log").read_text()
    assert "stop command from launcher" in env_log or "stop command from env" in env_log


def test_hammer_up_secure_flag_makes_a_secure_run(tmp_path):
    """`hammer up --secure` is `--runtime secure=true`: runtime.json says so, RUN/identity/ holds the
    peer run's identities (no hub), and the run completes; `--resume` cannot change it."""
    import json

    from tests.runtime_helpers import hammer

    run = tmp_path / "up"
    res = hammer("up", "--secure", "--episodes", "1", "--variant", "il", "--run-dir", str(run), "--no-dashboard")
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.startswith("done: 1 episodes in ")  # the verdict, on stdout
    assert json.loads((run / "runtime.json").read_text())["secure"] is True
    names = {p.name for p in (run / "identity").iterdir()}
    assert {"ca.pem", "launcher.pem", "env.key", "local-0.pem", "learner.key"} <= names
    assert not any(n.startswith("hub.") for n in names)
    # the rules every process applies, for a client in another language (docs/wire-format.md)
    from hammer.protocol.access import access_control

    rt = json.loads((run / "runtime.json").read_text())
    assert json.loads((run / "access_control.json").read_text()) == access_control(Keys(rt["run_id"]), 3)
    again = hammer("up", "--resume", str(run), "--secure")
    assert again.returncode == 2 and "only --episodes may be changed" in again.stderr and "--secure" in again.stderr


def test_router_hub_enforces_the_rules_for_its_clients(idents):
    """`hammer hub --run-dir` topology: clients reach each other only through the router, which
    checks every hop; a client with local-1's identity cannot act for agent 0 there either."""
    port = free_loopback_port()
    hub_t = TransportConfig(mode="router", listen=[f"tls/127.0.0.1:{port}"],
                            security=secure_link(idents, "hub", KEYS, N, router=True))

    def client(role: str) -> TransportConfig:
        return TransportConfig(mode="client", connect=[f"tls/127.0.0.1:{port}"],
                               security=secure_link(idents, role, KEYS, N, router=True))

    with HammerSession(RUN, hub_t, sender="hub"), HammerSession(RUN, client("env"), sender="env") as env, \
            HammerSession(RUN, client("local-0"), sender="local-0") as l0, \
            HammerSession(RUN, client("local-1"), sender="local-1") as l1:
        acts = env.subscribe_raw(KEYS.act("*"))
        spy = l1.subscribe_raw(KEYS.obs(0))
        obs0 = l0.subscribe_raw(KEYS.obs(0))
        _settle()
        for _ in range(20):
            l1.put_bytes(KEYS.act(0), b"forged")
        l1.put_bytes(KEYS.act(1), b"a1")
        l0.put_bytes(KEYS.act(0), b"a0")
        env.put_bytes(KEYS.obs(0), b"o0")
        assert sorted(_wait_for(acts, 2)) == [b"a0", b"a1"]
        assert _wait_for(obs0, 1) == [b"o0"]
        assert _late_extra(acts) == [] and _late_extra(spy, 0.1) == []


def test_hammer_hub_relays_only_a_run_made_for_a_router(tmp_path):
    """A peer run has no `hub` identity and its roles accept nothing relayed: `hammer hub --run-dir`
    refuses it in one line instead of starting a router nobody may use."""
    import json

    from hammer.runtime.settings import RuntimeSettings
    from typer.testing import CliRunner

    from hammer.cli import app

    RuntimeSettings(run_id="peers", secure=True).save(tmp_path)
    (tmp_path / "config.json").write_text(json.dumps({"n_agents": N}))
    res = CliRunner().invoke(app, ["hub", "--listen", "tcp/127.0.0.1:0", "--run-dir", str(tmp_path)])
    assert res.exit_code == 2 and "no secure_hub=true" in res.output, res.output
    with pytest.raises(ValueError, match="secure_hub=true needs secure=true"):
        RuntimeSettings(run_id="plain", secure_hub=True)
