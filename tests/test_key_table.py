"""Every key a role uses is one the docs list and the access rules grant it, in three places that must
agree: the role table `protocol.access.grants`, the table of docs/security.md ("Who may do what") and
the key table of docs/wire-format.md ("Key expressions"). Checked statically (the three tables against
each other), and against what real runs declare: a training run (`hammer up`), a lock-stepped served
run and a fleet that takes a push, each process writing the keys its session declared
(HAMMER_DECLARED_KEYS)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh
from hammer.protocol.access import LAUNCHER, POLICY, Grant, grants
from hammer.protocol.keys import Keys
from hammer.protocol.session import DECLARED_KEYS_ENV

from tests.runtime_helpers import ENV, ROOT

pytestmark = pytest.mark.timeout(420)
RUN = "r"
N = 3
DOCS = ROOT / "docs"


def _includes(expr: str, key: str) -> bool:
    return zenoh.KeyExpr(expr).includes(zenoh.KeyExpr(key))


def _rel(key: str, run: str = RUN) -> str:
    return key.removeprefix(f"hammer/{run}/")


def _wire_rows() -> list[re.Pattern]:
    """The key table of docs/wire-format.md as patterns over keys relative to hammer/<run>/ (a
    placeholder also matches a wildcard, as a role subscribing to every agent's key declares)."""
    text = (DOCS / "wire-format.md").read_text()
    section = text[text.index("## Key expressions"):text.index("## Message layout")]
    rows = re.findall(r"^\| `hammer/<run>/([^`]+)` \|", section, re.MULTILINE)
    assert len(rows) >= 15, rows
    out = []
    for row in rows:
        p = re.escape(row)
        for name, rx in (("agent", r"(\d+|\*)"), ("role", r"([A-Za-z0-9][A-Za-z0-9_.-]*|\*)"),
                         ("name", r"[A-Za-z0-9][A-Za-z0-9_.-]*")):
            p = p.replace(re.escape(f"<{name}>"), rx)
        out.append(re.compile(p))
    return out


def _security_rows() -> dict[str, list[list[str]]]:
    """docs/security.md's role table: role -> [publishes, subscribes to, answers] as the key items of
    each cell (a role's `<i>`: any agent index)."""
    text = (DOCS / "security.md").read_text()
    section = text[text.index("## Who may do what"):text.index("## What a thief")]
    rows = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 4 or not cells[0].startswith("`"):
            continue
        rows[cells[0].strip("`")] = [re.findall(r"`([a-z]+/[^`]*)`", c) for c in cells[1:]]
    return rows


def _doc_pattern(item: str) -> re.Pattern:
    return re.compile(re.escape(item).replace(re.escape("<i>"), r"\d+"))


def _role_row(role: str) -> str:
    return "local-<i>" if role.startswith("local-") else role


def test_the_access_rules_the_security_table_and_the_wire_key_table_agree():
    keys = Keys(RUN)
    table, wire = _security_rows(), _wire_rows()
    g = grants(keys, N)
    assert {_role_row(r) for r in g} == set(table) - {"hub"} - {r for r in table if r.startswith("locals-")}, table
    for role, grant in g.items():
        doc = table[_role_row(role)]
        for column, granted in zip(doc, (grant.publish, grant.subscribe, grant.answers), strict=True):
            rel = [_rel(k) for k in granted]
            for k in rel:  # every granted key is in the role's row of docs/security.md ...
                assert any(_doc_pattern(d).fullmatch(k) for d in column), (role, k, column)
                # ... and in the key table of docs/wire-format.md
                assert any(p.fullmatch(k) for p in wire), (role, k)
            for d in column:  # and the row names nothing the rules do not grant
                assert any(_doc_pattern(d).fullmatch(k) for k in rel), (role, d, rel)
        assert grant.liveliness == (() if role == LAUNCHER else (keys.alive(role),)), role
        assert grant.watch_liveliness == (role in (LAUNCHER, "learner")), role


# Declared by a role and denied by the rules on purpose, as the docs say: the env host's stop at the end
# of its budget ends a plain run whose roles were started by hand; a secure run keeps control to the
# launcher, which stops every role when the env host exits (docs/wire-format.md, "Stop semantics").
DENIED_ON_PURPOSE = {("env", "publish", "ctl/all")}


def test_what_is_denied_on_purpose_is_documented():
    assert "the env host's\nend-of-budget stop is then dropped by the rules" in (DOCS / "wire-format.md").read_text()
    assert "stop the run (its stop is not in the table: dropped)" in (DOCS / "security.md").read_text()


def _covered(grant: Grant, keys: Keys, kind: str, key: str) -> bool:
    if kind == "publish":
        return any(_includes(g, key) for g in grant.publish)
    if kind in ("subscribe", "query"):  # a query is allowed on what a role may receive
        return any(_includes(g, key) for g in grant.subscribe)
    if kind == "answer":
        return any(_includes(g, key) for g in grant.answers)
    if kind == "alive":
        return key in grant.liveliness
    return kind == "watch" and grant.watch_liveliness


def _check_declared(directory: Path, run: str, roles: set[str]) -> set[tuple[str, str, str]]:
    """Every key each process of `run` declared is granted to its role and in the wire key table;
    returns (role, kind, relative key) of all of them."""
    keys, wire, seen = Keys(run), _wire_rows(), set()
    g = grants(keys, N)
    files = [json.loads(p.read_text()) for p in directory.glob("*.json")]
    mine = [f for f in files if f["run"] == run]
    assert {f["sender"] for f in mine} == roles, sorted({f["sender"] for f in mine})
    wrong = set()
    for f in mine:
        for kind, key in f["declared"]:
            rel = _rel(key, run)
            if not _covered(g[f["sender"]], keys, kind, key) and (f["sender"], kind, rel) not in DENIED_ON_PURPOSE:
                wrong.add(("not granted", f["sender"], kind, rel))
            if kind not in ("alive", "watch") and not any(p.fullmatch(rel) for p in wire):
                wrong.add(("not in the wire key table", f["sender"], kind, rel))
            seen.add((f["sender"], kind, rel))
    assert not wrong, sorted(wrong)
    return seen


@pytest.fixture(scope="module")
def teams(tmp_path_factory):
    """A briefly trained cn3 team, and the same team with other local weights (declaring that it
    works with the first one's central network), for a push that must be pulled in chunks."""
    from tests.runtime_helpers import trained_pair

    return trained_pair(tmp_path_factory.mktemp("keys"))


def test_real_runs_declare_only_keys_their_roles_are_granted_and_the_docs_list(teams, tmp_path, monkeypatch):
    from hammer.deploy.fleet_launch import FleetPlan, run_fleet
    from hammer.serve.push import push

    bundle, pushed = teams
    declared = tmp_path / "declared"
    declared.mkdir()
    monkeypatch.setenv(DECLARED_KEYS_ENV, str(declared))
    env = {**ENV, DECLARED_KEYS_ENV: str(declared)}
    seen = set()

    # a training run: the learner, the experience keys
    r = subprocess.run([sys.executable, "-m", "hammer.cli", "up", "--episodes", "2", "--central-mode", "rl",
                        "--run-dir", str(tmp_path / "up"), "--no-dashboard"], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=240, check=False)
    assert r.returncode == 0, r.stderr[-3000:]
    run_id = json.loads((tmp_path / "up" / "runtime.json").read_text())["run_id"]
    seen |= _check_declared(declared, run_id, {"env", "central", "learner", LAUNCHER,
                                               *(f"local-{i}" for i in range(N))})

    # a lock-stepped served run: the policy server (`policy`, no learner) answers, the agents may ask
    r = subprocess.run([sys.executable, "-m", "hammer.cli", "serve", str(bundle), "--episodes", "8", "--run-dir",
                        str(tmp_path / "served"), "--no-dashboard"], cwd=ROOT, env=env, capture_output=True,
                       text=True, timeout=240, check=False)
    assert r.returncode == 0, r.stderr[-3000:]
    run_id = json.loads((tmp_path / "served" / "runtime.json").read_text())["run_id"]
    seen |= _check_declared(declared, run_id, {"env", "central", POLICY, LAUNCHER,
                                               *(f"local-{i}" for i in range(N))})

    # a fleet that takes a push: the world's state and the central messages it puts into the robots'
    # observations, the announcement, the chunks the robots ask for
    run = tmp_path / "fleet"
    done = {}

    def update(board, t: float) -> None:
        world = board.heartbeats.get("env")
        if "push" not in done and world is not None and world.counters.get("ticks", 0) >= 20:
            push(pushed, run)
            done["push"] = t

    s = run_fleet(FleetPlan(bundle=bundle, hz=20, seconds=9), run, on_tick=update)
    assert s["completed"] and "push" in done, s
    assert all(r["versions_pulled"] >= 1 for r in s["robots"].values()), s["robots"]
    seen |= _check_declared(declared, run.name.replace("_", "-"), {"env", "central", POLICY, LAUNCHER,
                                                                   *(f"local-{i}" for i in range(N))})

    # the runs used what they exist for (so the check above was not run on a subset)
    for expected in [("local-0", "subscribe", "learn/local/announce"), ("local-0", "query", "learn/local/chunk"),
                     ("env", "subscribe", "central/msg/*"), (POLICY, "answer", "learn/local/chunk"),
                     (POLICY, "publish", "learn/local/announce"), ("env", "subscribe", "learn/local/announce"),
                     ("central", "publish", "learn/central/exp"), ("learner", "subscribe", "learn/team/exp"),
                     ("central", "subscribe", "ctl/hb/local-0"), ("env", "subscribe", "ctl/hb/local-0")]:
        assert expected in seen, (expected, sorted(x for x in seen if x[0] == expected[0]))
