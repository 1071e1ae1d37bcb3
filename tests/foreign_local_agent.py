"""A hammer local agent written from docs/wire-format.md, docs/fleet.md and docs/deploy.md alone:
zenoh, msgpack, numpy, stdlib.

It imports nothing of the project on purpose (tests/test_foreign_client.py checks that): it is
what someone writing a local agent in another language would write, in Python only because the
test suite runs Python. Usage:

    python foreign_local_agent.py RUN_DIR AGENT
    python foreign_local_agent.py --fleet BUNDLE RUN_ID AGENT ENDPOINT

The first reads RUN_DIR/config.json, env_spec.json and runtime.json, connects to the hub of
`hammer up` or `hammer serve` on 127.0.0.1 (runtime.json hub_port), declares itself alive as
`local-AGENT`, acts on every observation with the policy version it names and the randomness
contract (so its actions equal those of `hammer local`), and exits 0 on a stop command from `launcher` or `env` (a stop from any other sender is
counted as rejected and ignored).

The second is robot AGENT of a fleet (`hammer serve BUNDLE --realtime HZ --external AGENT`): from the
bundle alone (its manifest, docs/deploy.md, and local.safetensors) and the hub's ENDPOINT, it acts on
each observation the world sends it with the central message that observation carries (else the
freshest it holds, if young enough), sends its action (no uplink: the world holds what it would
say), and takes a push to the fleet by pulling it in chunks, one per act.
"""

from __future__ import annotations

import hashlib
import json
import os
import queue
import struct
import sys
import time
from pathlib import Path

import msgpack
import numpy as np
import zenoh

SCHEMA_VERSION = 7
TAGS = {"local_obs": 1, "global_state": 2, "central_msg": 3, "action": 4, "experience": 5, "weights": 6,
        "control": 7, "heartbeat": 8, "uplink": 9, "weights_announce": 10, "weights_chunk": 11}
HEADER = ("v", "step", "env_idx", "sender")
# Each message's fields in wire order after the type tag, and the defaults of those that may be left off the end.
FIELDS = {
    "local_obs": (*HEADER, "agent", "obs", "policy_version", "echo", "active", "msg"),
    "central_msg": (*HEADER, "agent", "msg", "policy_version"),
    "action": (*HEADER, "agent", "action", "policy_version", "fallback", "msg"),
    "weights": (*HEADER, "role", "version", "blob", "sha256", "format"),
    "control": (*HEADER, "command", "target", "args"),
    "heartbeat": (*HEADER, "role", "pid", "status", "counters", "gauges", "detail"),
    "weights_announce": (*HEADER, "role", "version", "size", "sha256", "chunk_bytes", "digests", "format"),
    "weights_chunk": (*HEADER, "role", "version", "index", "data"),
}
DEFAULTS = {"policy_version": 0, "echo": False, "active": None, "fallback": None, "msg": None, "format": "safetensors",
            "target": "*", "args": {}, "counters": {}, "gauges": {}, "detail": ""}
CODES = {"bool": 0, "uint8": 1, "int32": 2, "int64": 3, "float16": 4, "float32": 5, "float64": 6}
DTYPES = {"float32": "<f4", "float64": "<f8", "int64": "<i8", "int32": "<i4", "uint8": "u1", "bool": "?",
          "float16": "<f2"}
ST_DTYPES = {"F32": "<f4", "F64": "<f8", "I64": "<i8", "I32": "<i4", "U8": "u1", "BOOL": "?"}
LOCAL_STREAM = 1  # the randomness contract: local agent i draws from default_rng([seed, 1, i])
STOP_SENDERS = ("launcher", "env")  # the only senders whose stop a role obeys


class Rejected(Exception):
    """A payload this client does not accept (skipped, counted)."""


# ----- wire format --------------------------------------------------------------------------------
def to_array(d: object, dtype: str, ndim: int) -> np.ndarray:
    """An array [dtype code, shape, data] of `dtype` (float32 fields may come as float16: read as float32)."""
    if not isinstance(d, list) or len(d) != 3:
        raise Rejected("expected an array [code, shape, data]")
    code, shape, data = d
    names = {CODES[dtype]: dtype} | ({CODES["float16"]: "float16"} if dtype == "float32" else {})
    if code not in names:
        raise Rejected(f"expected a {dtype} array")
    if not isinstance(shape, list) or len(shape) != ndim or not all(type(n) is int and n >= 0 for n in shape):
        raise Rejected(f"bad shape {shape!r}")
    dt = np.dtype(DTYPES[names[code]])
    if not isinstance(data, bytes) or len(data) != int(np.prod(shape)) * dt.itemsize:
        raise Rejected("data length disagrees with the shape")
    a = np.frombuffer(data, dt).reshape(shape).astype(DTYPES[dtype])
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        raise Rejected("non-finite floats")
    if a.dtype.kind == "b" and not set(data) <= {0, 1}:
        raise Rejected("bool bytes other than 0 / 1")
    return a


def from_array(a: np.ndarray, dtype: str) -> list:
    a = np.ascontiguousarray(a, dtype=DTYPES[dtype])
    return [CODES[dtype], list(a.shape), a.tobytes()]


def parse(payload: bytes, tag: str) -> dict:
    """The header checks every receiver makes; the message as a dict of its fields by name."""
    try:
        m = msgpack.unpackb(payload, raw=False, strict_map_key=True)
    except Exception as e:  # noqa: BLE001 - any malformed payload is rejected
        raise Rejected(f"not msgpack: {e}") from None
    fields = FIELDS[tag]
    if not isinstance(m, list) or len(m) < 2 or m[0] != TAGS[tag] or m[1] != SCHEMA_VERSION:
        raise Rejected("wrong version or type")
    if len(m) - 1 > len(fields) or any(f not in DEFAULTS for f in fields[len(m) - 1:]):
        raise Rejected("fields missing or too many")
    d = {**{f: DEFAULTS[f] for f in fields[len(m) - 1:]}, **dict(zip(fields, m[1:]))}
    if type(d["step"]) is not int or d["step"] < 0 or not isinstance(d["sender"], str):
        raise Rejected("bad step or sender")
    e = d["env_idx"]
    if type(e) is int and e >= 0:  # K: the copies 0..K-1
        d["env_idx"] = np.arange(e, dtype=np.int64)
    elif isinstance(e, list) and all(type(i) is int and i >= 0 for i in e) and len(set(e)) == len(e):
        d["env_idx"] = np.array(e, dtype=np.int64).reshape(-1)
    else:
        raise Rejected("bad env_idx")
    return d


def env_idx_to_wire(env_idx: np.ndarray) -> int | list[int]:
    k = len(env_idx)
    return k if np.array_equal(env_idx, np.arange(k)) else [int(i) for i in env_idx]


def header(tag: str, step: int, env_idx: np.ndarray) -> list:
    """The type tag and header of every message this agent sends; sender "": the one its key implies."""
    return [TAGS[tag], SCHEMA_VERSION, step, env_idx_to_wire(env_idx), ""]


# ----- the policy ---------------------------------------------------------------------------------
def read_safetensors(blob: bytes) -> dict[str, np.ndarray]:
    """safetensors: u64 little-endian header length, JSON header, then the tensors' bytes."""
    (n,) = struct.unpack("<Q", blob[:8])
    header = json.loads(blob[8:8 + n])
    data = blob[8 + n:]
    out = {}
    for name, t in header.items():
        if name == "__metadata__":
            continue
        b, e = t["data_offsets"]
        out[name] = np.frombuffer(data[b:e], ST_DTYPES[t["dtype"]]).reshape(t["shape"])
    return out


def layers(params: dict[str, np.ndarray], prefix: str) -> list[tuple[np.ndarray, np.ndarray]]:
    out, i = [], 0
    while f"{prefix}.layers.{i}.weight" in params:
        out.append((params[f"{prefix}.layers.{i}.weight"].astype(np.float32),
                    params[f"{prefix}.layers.{i}.bias"].astype(np.float32)))
        i += 1
    return out


def send_heartbeat(z, key: str, pub, hb: list, status: str) -> None:
    """Periodic heartbeats on the best-effort publisher; the last one (stopped) reliably, at once
    (docs/wire-format.md, "Being a role")."""
    data = msgpack.packb(hb, use_bin_type=True)
    if status == "stopped":
        z.put(key, data, congestion_control=zenoh.CongestionControl.DROP)
    else:
        pub.put(data)


class Policy:
    def __init__(self, params: dict[str, np.ndarray]) -> None:
        self.actor = layers(params, "actor")
        self.log_std = params.get("log_std")  # present only for continuous actions

    def actor_out(self, x: np.ndarray) -> np.ndarray:
        """x W^T + b per layer, tanh between layers, none after the last: logits or Gaussian mean."""
        for j, (w, b) in enumerate(self.actor):
            x = x @ w.T + b
            if j < len(self.actor) - 1:
                x = np.tanh(x)
        return x


# ----- the agent ----------------------------------------------------------------------------------
class ForeignLocalAgent:
    def __init__(self, run_dir: Path, agent: int) -> None:
        cfg = json.loads((run_dir / "config.json").read_text())
        spec = json.loads((run_dir / "env_spec.json").read_text())
        rt = json.loads((run_dir / "runtime.json").read_text())
        self.run_dir, self.agent, self.name = run_dir, agent, f"local-{agent}"
        self.run_id, self.n = rt["run_id"], cfg["n_agents"]
        self.discrete, self.action_dim = spec["discrete"], spec["action_dim"]
        self.msg_dim = cfg["msg_dim"] if cfg["variant"] in ("hammer", "random") else 0
        self.onehot = cfg["variant"] == "centralized"  # joint observation + one-hot(agent)
        self.fallback, self.fallback_k = rt["fallback"], rt["fallback_k"]
        self.msg_deadline_s, self.weights_timeout_s = rt["msg_deadline_ms"] / 1e3, rt["weights_timeout_s"]
        self.rng = np.random.default_rng([cfg["seed"], LOCAL_STREAM, agent])
        k = cfg["num_envs"]
        self.last_msg, self.msg_age = np.zeros((k, self.msg_dim), np.float32), np.zeros(k, np.int64)
        self.policy, self.version, self.held = None, -1, {}
        self.pending, self.last_step = {}, -1
        self.counters = {"steps": 0, "msgs_on_time": 0, "msgs_late": 0, "msgs_duplicate": 0, "fallback_copies": 0,
                         "obs_stale": 0, "rejected": 0}
        self.stop = False

        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
        conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{rt['hub_port']}"]))
        self.z = zenoh.open(conf)
        p = f"hammer/{self.run_id}"
        self.queues: dict[str, queue.SimpleQueue] = {}
        self.subs = [self._subscribe(name, key) for name, key in [
            ("obs", f"{p}/env/obs/{agent}"), ("weights", f"{p}/learn/local/weights"), ("ctl", f"{p}/ctl/all"),
            *([("msg", f"{p}/central/msg/{agent}")] if self.msg_dim else [])]]
        # What each key says about its payload (docs/wire-format.md, "Bound to its key"): anything else is rejected.
        self.binding = {"obs": {"agent": agent, "sender": "env"}, "msg": {"agent": agent, "sender": "central"},
                        "weights": {"role": "local", "sender": "learner"}, "ctl": {}}
        self.act_key, self.hb_key = f"{p}/agent/act/{agent}", f"{p}/ctl/hb/{self.name}"
        self.act_pub = self.z.declare_publisher(self.act_key, congestion_control=zenoh.CongestionControl.BLOCK,
                                                express=True)
        self.hb_pub = self.z.declare_publisher(self.hb_key, congestion_control=zenoh.CongestionControl.DROP)
        # Alive only once every subscription is in place: the launcher starts the env host after this.
        self.token = self.z.liveliness().declare_token(f"{p}/alive/{self.name}")
        self.last_hb = 0.0

    def _subscribe(self, name: str, key: str):
        q = self.queues[name] = queue.SimpleQueue()
        return self.z.declare_subscriber(key, lambda s: q.put(s.payload.to_bytes()))

    def take(self, name: str, tag: str, timeout: float = 0.0) -> dict | None:
        """The next accepted message of queue `name` within `timeout` s (None: nothing came)."""
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            try:
                raw = self.queues[name].get(timeout=left) if left > 0 else self.queues[name].get_nowait()
            except queue.Empty:
                return None
            try:
                m = parse(raw, tag)
            except Rejected:
                self.counters["rejected"] += 1
                continue
            # sender "": the one the key implies
            if all(m.get(k) == v or (k == "sender" and m[k] == "") for k, v in self.binding[name].items()):
                return m
            self.counters["rejected"] += 1

    # ----- inputs -------------------------------------------------------------------------------
    def on_control(self) -> None:
        while (c := self.take("ctl", "control")) is not None:
            if c.get("command") != "stop" or c.get("target") not in ("*", self.name):
                continue
            if c.get("sender") in STOP_SENDERS:  # docs/wire-format.md, "Stop semantics"
                self.stop = True
            else:
                self.counters["rejected"] += 1

    def on_weights(self, w: dict) -> None:
        blob, version = w.get("blob"), w.get("version")
        if not isinstance(blob, bytes) or hashlib.sha256(blob).hexdigest() != w.get("sha256"):
            self.counters["rejected"] += 1
        elif type(version) is int and version > self.version:
            self.held[version] = blob

    def preload(self) -> None:
        while (w := self.take("weights", "weights")) is not None:
            self.on_weights(w)
        if self.held:
            self.use_version(min(self.held))

    def use_version(self, need: int) -> None:
        """Load the newest held version <= need, waiting up to weights_timeout_s while we hold an older one."""
        deadline = time.monotonic() + self.weights_timeout_s
        while True:
            while (w := self.take("weights", "weights")) is not None:
                self.on_weights(w)
            usable = [v for v in self.held if v <= need]
            if usable:
                v = max(usable)
                self.policy, self.version = Policy(read_safetensors(self.held[v])), v
                self.held = {u: b for u, b in self.held.items() if u > v}
            if self.version >= need or time.monotonic() > deadline:
                return
            w = self.take("weights", "weights", timeout=0.05)
            if w is not None:
                self.on_weights(w)

    def message_for(self, step: int, env_idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """This step's message (waiting up to msg_deadline_ms), else the fallback; and the fallback mask."""
        deadline = time.monotonic() + self.msg_deadline_s
        while step not in self.pending:
            m = self.take("msg", "central_msg", timeout=max(deadline - time.monotonic(), 1e-6))
            if m is None:
                break
            if m["step"] in self.pending:
                self.counters["msgs_duplicate"] += 1
            elif m["step"] <= self.last_step:
                self.counters["msgs_late"] += 1
            else:  # this step's or a future step's: kept until its step comes
                try:
                    m["msg"] = to_array(m["msg"], "float32", 2)
                except Rejected:
                    self.counters["rejected"] += 1
                    continue
                if m["msg"].shape != (len(m["env_idx"]), self.msg_dim) or np.abs(m["msg"]).max(initial=0) > 1:
                    self.counters["rejected"] += 1
                    continue
                self.pending[m["step"]] = m
        got = self.pending.pop(step, None)
        for s in [s for s in self.pending if s < step]:
            del self.pending[s]
            self.counters["msgs_late"] += 1
        msg = np.zeros((len(env_idx), self.msg_dim), np.float32)
        have = np.zeros(len(env_idx), bool)
        if got is not None:
            rows = {int(e): j for j, e in enumerate(got["env_idx"])}
            for j, e in enumerate(env_idx):
                if int(e) in rows:
                    msg[j], have[j] = got["msg"][rows[int(e)]], True
            self.last_msg[env_idx[have]], self.msg_age[env_idx[have]] = msg[have], 0
            self.counters["msgs_on_time"] += 1
        miss = ~have
        if miss.any():
            idx = env_idx[miss]
            self.msg_age[idx] += 1
            if self.fallback != "zeros":
                fill = self.last_msg[idx].copy()
                if self.fallback == "last_k":
                    fill[self.msg_age[idx] > self.fallback_k] = 0.0
                msg[miss] = fill
            self.counters["fallback_copies"] += int(miss.sum())
        return msg, miss

    def on_obs(self, o: dict) -> None:
        step, env_idx = o["step"], o["env_idx"]
        if step <= self.last_step:
            self.counters["obs_stale"] += 1
            return
        obs = to_array(o["obs"], "float32", 2)
        self.use_version(o["policy_version"])
        k = len(env_idx)
        parts = [obs]
        if self.onehot:
            parts.append(np.tile(np.eye(self.n, dtype=np.float32)[self.agent], (k, 1)))
        msg, fallback = (self.message_for(step, env_idx) if self.msg_dim else (None, np.zeros(k, bool)))
        if msg is not None:
            parts.append(msg)
        out = self.policy.actor_out(np.concatenate(parts, axis=1).astype(np.float32))
        if self.discrete:  # inverse CDF of softmax (float64) at one uniform per env copy
            z = out.astype(np.float64)
            p = np.exp(z - z.max(axis=1, keepdims=True))
            p /= p.sum(axis=1, keepdims=True)
            u = self.rng.random(k)
            action = np.minimum((np.cumsum(p, axis=1) <= u[:, None]).sum(axis=1), self.action_dim - 1)
            wire_action = from_array(action, "uint8" if self.action_dim <= 256 else "int64")
        else:
            z = self.rng.standard_normal((k, self.action_dim))
            wire_action = from_array(out + np.exp(self.log_std) * z, "float32")
        m = [*header("action", step, env_idx), self.agent, wire_action, max(self.version, 0),
             from_array(fallback, "bool"), from_array(msg, "float32") if msg is not None and o["echo"] is True else None]
        self.act_pub.put(msgpack.packb(m, use_bin_type=True))
        self.last_step = step
        self.counters["steps"] += 1

    # ----- the loop -----------------------------------------------------------------------------
    def heartbeat(self, status: str = "running", force: bool = False) -> None:
        if not force and time.monotonic() - self.last_hb < 1.0:
            return
        self.last_hb = time.monotonic()
        hb = [*header("heartbeat", 0, np.zeros(0, np.int64)), self.name, os.getpid(), status, self.counters,
              {"policy_version": self.version}, "foreign client"]
        send_heartbeat(self.z, self.hb_key, self.hb_pub, hb, status)

    def run(self) -> None:
        while not self.stop:
            self.heartbeat()
            o = self.take("obs", "local_obs", timeout=0.2)
            if o is not None:
                try:
                    self.on_obs(o)
                except (Rejected, KeyError, TypeError, ValueError):  # a field missing or of the wrong type
                    self.counters["rejected"] += 1
            elif self.version < 0:  # idle without a policy: load the first one now
                self.preload()
            self.on_control()
        self.heartbeat("stopped", force=True)
        counters = {**self.counters, "policy_version": self.version}
        try:  # final counters for the launcher's links.json, when we share the run directory
            (self.run_dir / "counters").mkdir(exist_ok=True)
            (self.run_dir / "counters" / f"{self.name}-{os.getpid()}.json").write_text(
                json.dumps({"role": self.name, "pid": os.getpid(), "counters": counters}))
        except OSError:
            pass
        print(f"{self.name} stopped: {json.dumps(counters)}", file=sys.stderr, flush=True)
        self.token.undeclare()
        self.z.close()


# ----- a robot of a fleet (docs/fleet.md) ---------------------------------------------------------
CHUNK_RETRY_S = 2.0  # a chunk asked for and not answered in this long is asked again (docs/wire-format.md)


class Pull:
    """A pushed version, pulled in chunks (docs/wire-format.md, "A pushed version, in chunks")."""

    def __init__(self, a: dict) -> None:
        self.version, self.size, self.sha256 = a["version"], a["size"], a["sha256"]
        self.chunk_bytes, self.digests = a["chunk_bytes"], a["digests"]
        self.n = -(-self.size // self.chunk_bytes)
        self.chunks: dict[int, bytes] = {}
        self.asked_at: float | None = None  # the one query outstanding

    def next_index(self) -> int:
        return min(i for i in range(self.n) if i not in self.chunks)

    def take(self, c: dict) -> str | None:
        """Keep a chunk of this version; the reason it is refused, else None."""
        i, data = c["index"], c["data"]
        if type(i) is not int or not 0 <= i < self.n or not isinstance(data, bytes):
            return "index or data"
        want = self.chunk_bytes if i < self.n - 1 else self.size - self.chunk_bytes * (self.n - 1)
        if len(data) != want:
            return f"{len(data)} bytes, expected {want}"
        if hashlib.sha256(data).digest()[:8] != self.digests[8 * i:8 * i + 8]:
            return "digest"
        self.chunks[i] = data
        return None


class ForeignRobot:
    def __init__(self, bundle: Path, run_id: str, agent: int, endpoint: str, max_msg_age_s: float = 0.5) -> None:
        m = json.loads((bundle / "manifest.json").read_text())
        spec = m["env_spec"]
        blob = (bundle / "local.safetensors").read_bytes()
        if hashlib.sha256(blob).hexdigest() != m["files"]["local.safetensors"]:
            raise SystemExit("local.safetensors differs from the manifest's sha256")
        self.agent, self.name, self.max_msg_age_s = agent, f"local-{agent}", max_msg_age_s
        self.obs_dim, self.discrete, self.action_dim = spec["obs_dim"], spec["discrete"], spec["action_dim"]
        self.msg_dim = m["msg_dim"]
        self.fallback, self.fallback_k = m["fallback"]["mode"], m["fallback"]["k"]
        self.rng = np.random.default_rng([m["config"]["seed"], LOCAL_STREAM, agent])
        self.blobs = {0: blob}  # version -> local weights held; the bundle's are the run's first (0)
        self.policy, self.version = Policy(read_safetensors(blob)), 0
        self.pull: Pull | None = None
        self.msg, self.msg_t, self.last_msg, self.msg_age = None, 0.0, np.zeros((1, self.msg_dim), np.float32), 0
        self.ages: list[float] = []
        self.counters = {"acts": 0, "msg_fresh": 0, "msg_stale": 0, "msg_none": 0, "msgs_received": 0,
                         "uplinks_sent": 0, "policy_switches": 0, "weights_rejected": 0, "chunk_queries": 0,
                         "chunks_received": 0, "chunks_refused": 0, "versions_pulled": 0, "rejected": 0}
        self.stop = False

        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        self.z = zenoh.open(conf)
        self.p = p = f"hammer/{run_id}"
        self.queues: dict[str, queue.SimpleQueue] = {}
        self.subs = [self._subscribe(name, key) for name, key in [
            ("obs", f"{p}/env/obs/{agent}"),
            ("weights", f"{p}/learn/local/weights"), ("announce", f"{p}/learn/local/announce"),
            ("ctl", f"{p}/ctl/all")]]
        self.queues["chunk"] = queue.SimpleQueue()  # replies to our chunk queries
        self.binding = {"obs": {"agent": agent, "sender": "env"},
                        "weights": {"role": "local", "sender": "learner"},
                        "announce": {"role": "local", "sender": "learner"},
                        "chunk": {"role": "local", "sender": "learner"}, "ctl": {}}
        # A fleet's streams: reliable, congestion control DROP, express (docs/fleet.md): a dead link
        # drops our messages instead of holding up the robot.
        drop = zenoh.CongestionControl.DROP
        self.act_pub = self.z.declare_publisher(f"{p}/agent/act/{agent}", congestion_control=drop, express=True)
        self.hb_key = f"{p}/ctl/hb/{self.name}"
        self.hb_pub = self.z.declare_publisher(self.hb_key, congestion_control=drop,
                                               reliability=zenoh.Reliability.BEST_EFFORT)
        self.token = self.z.liveliness().declare_token(f"{p}/alive/{self.name}")
        self.last_hb = 0.0

    _subscribe = ForeignLocalAgent._subscribe
    take = ForeignLocalAgent.take
    on_control = ForeignLocalAgent.on_control

    # ----- weights: whole publications, and a push in chunks ----------------------------------------
    def take_weights(self) -> None:
        while (w := self.take("weights", "weights")) is not None:
            blob, version = w.get("blob"), w.get("version")
            if not isinstance(blob, bytes) or hashlib.sha256(blob).hexdigest() != w.get("sha256"):
                self.counters["weights_rejected"] += 1
            elif type(version) is int and version not in self.blobs:
                self.blobs[version] = blob
        while (a := self.take("announce", "weights_announce")) is not None:
            v = a.get("version")
            if type(v) is not int or v <= max(self.blobs) or (self.pull is not None and v <= self.pull.version):
                continue  # a repeat, or not newer than what we hold
            size, cb, dg = a.get("size"), a.get("chunk_bytes"), a.get("digests")
            if not (type(size) is int and type(cb) is int and size > 0 and cb > 0 and isinstance(dg, bytes)
                    and len(dg) == 8 * -(-size // cb)):
                self.counters["weights_rejected"] += 1
                continue
            same = [b for b in self.blobs.values() if hashlib.sha256(b).hexdigest() == a["sha256"]]
            if same:  # bytes we hold already (a rollback): held as that version, no pull
                self.blobs[v], self.pull = same[0], None
                self.heartbeat(force=True)
            else:
                self.pull = Pull(a)

    def pump(self) -> None:
        """One chunk asked for per act, one query outstanding (docs/wire-format.md)."""
        pull = self.pull
        if pull is None:
            return
        while (c := self.take("chunk", "weights_chunk")) is not None:
            if c.get("version") != pull.version:
                continue
            why = pull.take(c)
            self.counters["chunks_received" if why is None else "chunks_refused"] += 1
            pull.asked_at = None
        if len(pull.chunks) == pull.n:
            blob = b"".join(pull.chunks[i] for i in range(pull.n))
            self.pull = None
            if hashlib.sha256(blob).hexdigest() != pull.sha256:
                self.counters["weights_rejected"] += 1
                return
            self.blobs[pull.version] = blob
            self.counters["versions_pulled"] += 1
            self.heartbeat(force=True)  # policy_held: the central agent waits for it
            return
        if pull.asked_at is None or time.monotonic() - pull.asked_at > CHUNK_RETRY_S:
            q = self.queues["chunk"]
            pull.asked_at = time.monotonic()
            self.counters["chunk_queries"] += 1
            self.z.get(f"{self.p}/learn/local/chunk?v={pull.version}&i={pull.next_index()}",
                       lambda r: q.put(r.ok.payload.to_bytes()) if r.ok is not None else None, timeout=CHUNK_RETRY_S)

    def switch(self) -> None:
        """A fleet has no step that names a version: act with the newest held from now on."""
        newest = max(self.blobs)
        if newest != self.version:
            self.policy, self.version = Policy(read_safetensors(self.blobs[newest])), newest
            self.counters["policy_switches"] += 1
            self.heartbeat(force=True)
            self.blobs = {v: b for v, b in self.blobs.items() if v >= newest or v == 0}

    # ----- one act ----------------------------------------------------------------------------------
    def message(self, o: dict) -> tuple[np.ndarray, bool]:
        """The central message the observation carries, else the newest held (no step to match in a
        fleet), if young enough."""
        if o.get("msg") is not None:
            msg = to_array(o["msg"], "float32", 2)
            if msg.shape != (1, self.msg_dim) or np.abs(msg).max(initial=0) > 1:
                raise Rejected("central message shape or range")
            self.msg, self.msg_t = msg, time.monotonic()
            self.counters["msgs_received"] += 1
        if self.msg is None:
            self.counters["msg_none"] += 1
        else:
            age = time.monotonic() - self.msg_t
            self.ages = [*self.ages[-1023:], age]
            if age <= self.max_msg_age_s:
                self.counters["msg_fresh"] += 1
                self.last_msg, self.msg_age = self.msg, 0
                return self.msg, True
            self.counters["msg_stale"] += 1
        self.msg_age += 1
        if self.fallback == "zeros" or (self.fallback == "last_k" and self.msg_age > self.fallback_k):
            return np.zeros((1, self.msg_dim), np.float32), False
        return self.last_msg, False

    def act(self, o: dict) -> None:
        obs = to_array(o["obs"], "float32", 2)
        if obs.shape != (1, self.obs_dim):
            raise Rejected("observation shape")
        msg, fresh = self.message(o) if self.msg_dim else (None, False)
        self.take_weights()
        self.pump()
        self.switch()
        out = self.policy.actor_out(np.concatenate([obs, msg], axis=1) if msg is not None else obs)
        if self.discrete:
            z = out.astype(np.float64)
            p = np.exp(z - z.max(axis=1, keepdims=True))
            p /= p.sum(axis=1, keepdims=True)
            action = np.minimum((np.cumsum(p, axis=1) <= self.rng.random(1)[:, None]).sum(axis=1), self.action_dim - 1)
            wire_action = from_array(action, "uint8" if self.action_dim <= 256 else "int64")
        else:
            action = (out + np.exp(self.policy.log_std) * self.rng.standard_normal((1, self.action_dim)))
            wire_action = from_array(action, "float32")
        a = [*header("action", o["step"], o["env_idx"]), self.agent, wire_action, self.version,
             from_array(np.array([not fresh]), "bool"),
             from_array(msg, "float32") if msg is not None and o["echo"] is True else None]
        self.act_pub.put(msgpack.packb(a, use_bin_type=True))
        self.counters["acts"] += 1

    def heartbeat(self, status: str = "running", force: bool = False) -> None:
        if not force and time.monotonic() - self.last_hb < 1.0:
            return
        self.last_hb = time.monotonic()
        held = max(self.blobs)
        gauges = {"policy_version": self.version, "policy_held": held,
                  "policy_pulling": -1 if self.pull is None else self.pull.version}
        if self.ages:
            p50, p99 = np.percentile(self.ages, [50, 99]) * 1e3
            gauges.update(msg_age_p50_ms=round(float(p50), 2), msg_age_p99_ms=round(float(p99), 2))
        hb = [*header("heartbeat", 0, np.zeros(0, np.int64)), self.name, os.getpid(), status, self.counters, gauges,
              "foreign robot"]
        send_heartbeat(self.z, self.hb_key, self.hb_pub, hb, status)

    def run(self) -> None:
        while not self.stop:
            self.heartbeat()
            newest = None
            while (o := self.take("obs", "local_obs", timeout=0.0 if newest else 0.2)) is not None:
                newest = o  # one act per observation the world sent: the newest, when several queued
            if newest is not None:
                try:
                    self.act(newest)
                except (Rejected, KeyError, TypeError, ValueError):
                    self.counters["rejected"] += 1
            self.on_control()
        self.heartbeat("stopped", force=True)
        print(f"{self.name} stopped: {json.dumps(self.counters)}", file=sys.stderr, flush=True)
        self.token.undeclare()
        self.z.close()


if __name__ == "__main__":
    if sys.argv[1] == "--fleet":
        ForeignRobot(Path(sys.argv[2]), sys.argv[3], int(sys.argv[4]), sys.argv[5]).run()
    else:
        ForeignLocalAgent(Path(sys.argv[1]), int(sys.argv[2])).run()
