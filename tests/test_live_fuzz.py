"""Live fuzz: malformed and mutated messages on every key of a running `hammer up` (loopback).

Hypothesis (derandomized, a bounded number of examples) mutates a valid message of each key's
type, built with the run's real dimensions: random bytes, flipped / cut / inserted bytes, a field
replaced, dropped or added, an array's dtype, shape or bytes changed (NaN included). Only
payloads the key's receiver rejects are kept (decided by the receiver's own decode, with its
type, declared dimensions and run id), so nothing valid (a forged stop, a far-future step) is
injected: this test is about robustness, not about forgeries (tests/test_key_binding.py has those). They are
published while the run steps; the run must complete, and every receiver must have counted each
payload under the reason the decoder gives it (the subscription logs its first 10 rejections per
reason, numbered; the learner reports its total as `bad_chunks`).
"""

from __future__ import annotations

import collections
import json
import re
import socket
import subprocess
import sys
import time
from dataclasses import dataclass

import msgpack
import numpy as np
from hammer.envs.registry import make_vec_env
from hammer.learning.config import merge_config
from hammer.protocol import codec
from hammer.protocol.binding import check_key
from hammer.protocol.dims import Dims
from hammer.protocol.errors import ProtocolError
from hammer.protocol.keys import Keys
from hammer.protocol.rollout_layout import CHUNK, RECORD, RolloutLayout
from hammer.protocol.schemas import (
    Action,
    CentralMsg,
    Control,
    ExperienceChunk,
    GlobalState,
    Heartbeat,
    LocalObs,
    Message,
    Weights,
)
from hammer.protocol.session import HammerSession, TransportConfig, free_loopback_port
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.runtime_helpers import ENV, ROOT, processes_mentioning

EXAMPLES = 200
RUN = "fuzz"
EPISODES = 96  # 3 rollouts of 32 episodes: the junk is taken in during the first one, and updates follow it
LOGGED = 10  # a subscription logs its first 10 rejections per reason (then every 1000th)
LINE = re.compile(r"rejected message #(\d+) \((\w+)\) on (\S+):")


@dataclass(frozen=True)
class Target:
    """One key, what its receivers expect, and the logs their rejections go to."""

    key: str
    sub: str  # the receivers' subscription key expression
    expected: type[Message]
    dims: Dims | None
    logs: tuple[str, ...]  # role names, "launcher" for hammer up's own stderr
    base: bytes  # a valid message of this key, to mutate

    def reason(self, payload: bytes) -> str | None:
        """The reason its receivers reject `payload`, None if they would accept it."""
        if self.dims is not None and len(payload) > self.expected.cap_for_dims(self.dims):
            return "size"  # refused on arrival: over what a message of the receiver's sizes can weigh
        try:
            msg = codec.decode(payload, self.expected)
            check_key(msg, Keys(RUN).relative(self.key))  # in the receiver's order: key, then declared dims
            if self.dims is not None:
                msg.check_dims(self.dims)
        except ProtocolError as e:
            return e.reason
        return None


def _targets() -> list[Target]:
    cfg = merge_config("cn3", overrides=["variant=hammer", "central_mode=rl"])
    env = make_vec_env(cfg.env, cfg.n_agents, 1)
    spec = env.spec
    env.close()
    k, n, d, m, a = cfg.num_envs, cfg.n_agents, spec.obs_dim, cfg.msg_dim, spec.action_dim
    keys, rng = Keys(RUN), np.random.default_rng(0)
    idx = np.arange(k, dtype=np.int64)
    locals_ = [f"local-{i}" for i in range(n)]
    local_dims = Dims(num_envs=k, n_agents=n, obs_dim=d, msg_dim=m, action_dim=a, discrete=True)
    layout = RolloutLayout.from_config(cfg, spec)
    learner_dims = Dims.from_layout(layout)

    def enc(msg: Message) -> bytes:
        return codec.encode(msg, stamp={"sender": "fuzz"})

    def f32(*shape: int) -> np.ndarray:
        return rng.standard_normal(shape).astype(np.float32)

    h = {"step": 3, "env_idx": idx}
    out = []
    for i in range(n):
        out += [
            Target(keys.obs(i), keys.obs(i), LocalObs, local_dims, (locals_[i],),
                   enc(LocalObs(**h, agent=i, obs=f32(k, d), active=np.ones(k, bool)))),
            Target(keys.msg(i), keys.msg(i), CentralMsg, local_dims, (locals_[i],),
                   enc(CentralMsg(**h, agent=i, msg=np.tanh(f32(k, m))))),
            Target(keys.act(i), keys.act("*"), Action,
                   Dims(num_envs=k, n_agents=n, action_dim=a, discrete=True, msg_dim=m, echo=True), ("env",),
                   enc(Action(**h, agent=i, action=rng.integers(0, a, k), fallback=np.zeros(k, bool),
                              msg=np.zeros((k, m), np.float32)))),
        ]
    chunk = {name: rng.random(arr.shape).astype(arr.dtype) if arr.dtype.kind == "f" else arr
             for name, arr in layout.allocate(CHUNK).items()}
    out += [
        Target(keys.state(), keys.state(), GlobalState,
               Dims(num_envs=k, n_agents=n, obs_dim=d, action_dim=a, discrete=True), ("central",),
               enc(GlobalState(**h, obs=f32(k, n, d), prev_actions=np.zeros((k, n, a), np.float32),
                               active=np.ones((k, n), bool)))),
        Target(keys.exp("team"), keys.exp("team"), ExperienceChunk, learner_dims, ("learner",),
               enc(ExperienceChunk(**h, role="team", policy_version=0, arrays=chunk))),
        Target(keys.exp("central"), keys.exp("central"), ExperienceChunk, learner_dims, ("learner",),
               enc(ExperienceChunk(**h, role="central", policy_version=0, arrays=layout.allocate(RECORD)))),
        Target(keys.weights("local"), keys.weights("local"), Weights, None, (*locals_, "env"),
               enc(Weights.from_blob("local", 1, rng.bytes(256)))),
        Target(keys.weights("central"), keys.weights("central"), Weights, None, ("central",),
               enc(Weights.from_blob("central", 1, rng.bytes(256)))),
        # the launcher reads ctl/all too: the env host's stop ends its attendance record (deploy/attendance.py)
        Target(keys.ctl("all"), keys.ctl("all"), Control, None, ("env", "central", "learner", "launcher", *locals_),
               enc(Control(command="stop", target="nobody"))),
        *(Target(keys.heartbeat(r), keys.heartbeat("*"), Heartbeat, None, ("launcher",),
                 enc(Heartbeat(role=r, pid=1, status="running", counters={"steps": 1})))
          for r in ("env", "local-0")),
    ]
    return out


_scalars = st.one_of(st.none(), st.booleans(), st.integers(-(2**63), 2**64 - 1), st.floats(),
                     st.text(max_size=8), st.binary(max_size=16))
_values = st.recursive(_scalars, lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=6), c,
                                                                                         max_size=4), max_leaves=8)
_NAN32 = np.array([np.nan], np.float32).tobytes()


def _is_array(v: object) -> bool:
    return isinstance(v, list) and len(v) == 3 and type(v[0]) is int and isinstance(v[2], bytes)


def _array_paths(d: list) -> list[tuple]:
    """Where the arrays of a decoded message are: a field (by position), or inside `arrays` (a map)."""
    paths: list[tuple] = [(i,) for i, v in enumerate(d) if _is_array(v)]
    for i, v in enumerate(d):
        if isinstance(v, dict) and v and all(_is_array(a) for a in v.values()):
            paths += [(i, name) for name in v]
    return paths


_CODES = {"float32": 5, "float64": 6, "int64": 3, "int32": 2, "uint8": 1, "bool": 0, "float16": 4}


@st.composite
def mutated(draw, base: bytes) -> bytes:
    kind = draw(st.sampled_from(["bytes", "flip", "truncate", "insert", "field", "drop", "extra", "array",
                                 "header"]))
    if kind == "bytes":
        return draw(st.binary(max_size=256))
    if kind in ("flip", "truncate", "insert"):
        i = draw(st.integers(0, len(base) - 1))
        if kind == "flip":
            b = bytearray(base)
            b[i] ^= draw(st.integers(1, 255))
            return bytes(b)
        if kind == "truncate":
            return base[:i]
        return base[:i] + draw(st.binary(min_size=1, max_size=8)) + base[i:]
    d = msgpack.unpackb(base, raw=False)  # [type tag, v, step, env_idx, sender, fields...]
    if kind == "array" and not _array_paths(d):
        kind = "field"  # a message without arrays (weights, control, heartbeat): replace a field instead
    if kind == "field":
        d[draw(st.integers(0, len(d) - 1))] = draw(_values)
    elif kind == "drop":
        del d[draw(st.integers(0, len(d) - 1))]
    elif kind == "header":  # well-formed, but another schema version or type; a corrupted blob; a long sender
        part = draw(st.sampled_from(["v", "type", "blob", "sender"]))
        if part == "v":
            d[1] = draw(st.sampled_from([1, 3, 2**31]))
        elif part == "type":
            d[0] = draw(st.sampled_from([1, 4, 6, 7, 2, 99, "local_obs"]))
        elif part == "blob" and d[0] == Weights.TAG:
            i = next(i for i, v in enumerate(d) if isinstance(v, bytes))
            d[i] = d[i][:-1] + bytes([d[i][-1] ^ 1])
        else:
            d[4] = "x" * 129
    elif kind == "extra":
        d.append(draw(_values))
    else:
        path = draw(st.sampled_from(_array_paths(d)))
        arr = d[path[0]] if len(path) == 1 else d[path[0]][path[1]]
        part = draw(st.sampled_from(["dtype", "shape", "data", "nan"]))
        if part == "dtype":
            arr[0] = draw(st.sampled_from([*_CODES.values(), 7, 255, "float32"]))
        elif part == "shape":
            arr[1] = draw(st.lists(st.integers(-2, 40), max_size=9))
        elif part == "data":
            arr[2] = draw(st.binary(max_size=64))
        elif arr[0] == _CODES["float32"] and len(arr[2]) >= 4:
            j = 4 * draw(st.integers(0, len(arr[2]) // 4 - 1))
            arr[2] = arr[2][:j] + _NAN32 + arr[2][j + 4:]
        else:
            arr[2] = arr[2] + b"\x00"
    return msgpack.packb(d, use_bin_type=True)


def _payloads(targets: list[Target]) -> list[tuple[Target, str, bytes]]:
    """(target, reason, payload) for every generated payload the target's receivers reject."""
    out = []

    @settings(max_examples=EXAMPLES, derandomize=True, database=None, deadline=None,
              suppress_health_check=list(HealthCheck))
    @given(st.data())
    def generate(data):
        t = data.draw(st.sampled_from(targets))
        payload = data.draw(mutated(t.base))
        reason = t.reason(payload)
        if reason is not None:
            out.append((t, reason, payload))

    generate()
    return out


def _logged_rejections(text: str) -> dict[tuple[str, str], int]:
    """(subscription key, reason) -> the highest rejection number logged."""
    seen: dict[tuple[str, str], int] = {}
    for n, reason, key in LINE.findall(text):
        seen[(key, reason)] = max(seen.get((key, reason), 0), int(n))
    return seen


def _wait_listening(port: int, proc: subprocess.Popen, timeout: float = 120) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            return
        except OSError:
            time.sleep(0.1)
    raise AssertionError(f"nothing listens on 127.0.0.1:{port} (hammer up exited: {proc.poll()})")


def test_live_fuzz_on_every_key_is_rejected_counted_and_the_run_completes(tmp_path):
    targets = _targets()
    payloads = _payloads(targets)
    assert len(payloads) >= EXAMPLES // 2
    assert {t.key for t, _, _ in payloads} == {t.key for t in targets}  # every key gets some
    assert len({r for _, r, _ in payloads}) >= 6  # and many kinds of fault (decode, field, shape, ...)

    run, port = tmp_path / RUN, free_loopback_port()
    up = subprocess.Popen(
        [sys.executable, "-m", "hammer.cli", "up", "--episodes", str(EPISODES), "--central-mode", "rl",
         "--run-dir", str(run), "--no-dashboard", "--runtime", f"hub_port={port}"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=ENV)
    try:
        _wait_listening(port, up)  # the launcher's hub session, before ours connects to it
        with HammerSession(RUN, TransportConfig.connector(port), sender="fuzz") as s:
            env_hb = s.subscribe(s.keys.heartbeat("env"), Heartbeat)
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline:  # the env host is stepping: every role is up
                hb = env_hb.get(timeout=0.5)
                if hb is not None and hb.counters.get("step", 0) >= 1:
                    break
            else:
                raise AssertionError("the run did not start stepping")
            for t, _, payload in payloads:
                s.put_bytes(t.key, payload)
            time.sleep(0.5)  # reliable puts are on their way before the session closes
        out, err = up.communicate(timeout=300)
    finally:
        if up.poll() is None:
            up.kill()
            up.communicate()
    assert up.returncode == 0, err[-3000:]
    assert f"done: {EPISODES} episodes" in out
    summary = json.loads((run / "summary.json").read_text())
    assert summary["completed"] and summary["episodes"] == EPISODES

    # Each receiver counted each payload under the decoder's reason.
    sent: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    for t, reason, _ in payloads:
        for role in t.logs:
            sent[role][(t.sub, reason)] += 1
    for role, counts in sent.items():
        text = err if role == "launcher" else (run / "logs" / f"{role}.log").read_text()
        expected = {k: min(n, LOGGED) for k, n in counts.items()}
        assert _logged_rejections(text) == expected, role
    learner = json.loads((run / "learner_summary.json").read_text())
    assert learner["bad_chunks"] == sum(1 for t, _, _ in payloads if t.expected is ExperienceChunk)
    per_update = 25 * 32 * 3
    assert learner["samples"] == learner["updates"] * per_update  # nothing junk was trained on
    assert processes_mentioning(str(run)) == []
