"""A trained team as a self-contained, versioned bundle: what serving and an edge agent need, no run directory.

    BUNDLE/manifest.json        bundle format, wire SCHEMA_VERSION, env id/kwargs/spec, variant, central
                                mode and network (concat | set), message length, fallback, the run it came from (+ final metric),
                                the full RunConfig, sha256 of every other file, and its seal: the sha256 of
                                all of that (format 2), so no field changes unnoticed
    BUNDLE/manifest.sig         optional: an ed25519 signature of manifest.json (serve/signing.py)
    BUNDLE/local.safetensors    the shared local policy (numpy dict, never pickle)
    BUNDLE/central.safetensors  the central agent (variants with a central network)

A bundle is read once, checked whole before anything uses it: a newer format, another wire schema,
a file whose hash differs, or weights whose shapes do not fit the env's dimensions each fail in one
line naming the field and the fix. Torch-free (json, hashlib, numpy, safetensors): an edge device
loads it with the base install.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hammer.protocol.schemas import SCHEMA_VERSION

BUNDLE_FORMAT = 2  # 2: the manifest carries its seal (format 1 bundles load, unsealed)
MANIFEST = "manifest.json"
LOCAL, CENTRAL = "local.safetensors", "central.safetensors"
SPEC_FIELDS = ("name", "n_agents", "obs_dim", "discrete", "action_dim")  # what the weights must fit


class BundleError(ValueError):
    """The bundle cannot be used; the message is the one-line reason and its fix."""


MANIFEST_FIELDS = ("bundle_format", "schema_version", "created_at", "env", "env_spec", "variant", "central_mode",
                   "central_net", "msg_dim", "local_input_dim", "fallback", "source", "config", "files", "seal",
                   "works_with_central")
RUN_CHOICES = {"num_envs": "--num-envs K", "seed": "--seed S", "episodes": "--episodes N"}  # set when serving
FALLBACKS = ("zeros", "last", "last_k")


def _count(value: Any, low: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= low


def check_manifest(m: dict[str, Any], mf: Path) -> None:
    """Every manifest value a server or an edge agent reads, checked for its type and range, before its
    seal (a hand edit with a wrong value is named by its field; one with a plausible value by the
    seal; a format-1 bundle has no seal, and the edge agent reads it without the RunConfig's
    validation), so a wrong value fails here, not later as messages every role rejects (an edge
    agent acting on K=1 copies of a K=32 run)."""
    def bad(field: str, value: Any, want: str, fix: str = "export the bundle again") -> BundleError:
        return BundleError(f"{mf}: {field} {value!r} {want}; fix: {fix}")

    for k, value in m.items():
        if k not in MANIFEST_FIELDS:
            hint = (f"it is chosen when serving, not in the manifest: remove it and pass {RUN_CHOICES[k]} to "
                    "hammer serve (and hammer local --bundle)" if k in RUN_CHOICES else "remove it, or export the "
                    "bundle again")
            raise bad(k, value, "is not a manifest field", hint)
    env, cfg = m["env_spec"], m["config"]
    for field, value in (("env_spec", env), ("config", cfg), ("files", m["files"])):
        if not isinstance(value, dict):
            raise bad(field, value, "must be a JSON object")
    for field, low in (("n_agents", 1), ("obs_dim", 1), ("action_dim", 1)):
        if not _count(env.get(field), low):
            raise bad(f"env_spec.{field}", env.get(field), f"must be an integer >= {low}")
    if not isinstance(env.get("discrete"), bool):
        raise bad("env_spec.discrete", env.get("discrete"), "must be true or false")
    if not isinstance(env.get("name"), str):
        raise bad("env_spec.name", env.get("name"), "must be a string")
    for field, low in (("msg_dim", 0), ("local_input_dim", 1)):
        if not _count(m[field], low):
            raise bad(field, m[field], f"must be an integer >= {low}")
    if not isinstance(m["variant"], str):
        raise bad("variant", m["variant"], "must be a string")
    if not _count(cfg.get("num_envs"), 1):
        raise bad("config.num_envs", cfg.get("num_envs"), "must be an integer >= 1 (env copies K)",
                  "set the trained value back (serve with --num-envs K to change it)")
    if not _count(cfg.get("seed"), 0):
        raise bad("config.seed", cfg.get("seed"), "must be an integer >= 0", "set it back (serve with --seed S)")
    for field, want in (("n_agents", env["n_agents"]), ("variant", m["variant"])):
        if cfg.get(field) != want:
            raise bad(f"config.{field}", cfg.get(field), f"differs from the manifest's {want!r}")
    fb = m.get("fallback", {})
    if not isinstance(fb, dict) or fb.get("mode", "zeros") not in FALLBACKS or not _count(fb.get("k", 3), 0):
        raise bad("fallback", fb, f"must be {{mode: {' | '.join(FALLBACKS)}, k: integer >= 0}}")
    for name, digest in m["files"].items():
        if not isinstance(digest, str) or len(digest) != 64:
            raise bad(f"files.{name}", digest, "must be a sha256 (64 hex digits)")
    ww = m.get("works_with_central", [])
    if not isinstance(ww, list) or not all(isinstance(d, str) and len(d) == 64 for d in ww):
        raise bad("works_with_central", ww, "must be a list of sha256 digests of central.safetensors files")


def seal(m: dict[str, Any]) -> str:
    """The sha256 of the manifest without its seal, as canonical JSON (sorted keys, no spaces): what
    makes every field of the manifest, the config included, part of the integrity check."""
    rest = {k: v for k, v in m.items() if k != "seal"}
    return hashlib.sha256(json.dumps(rest, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _weight_shapes(path: Path) -> dict[str, tuple[int, ...]]:
    """Tensor shapes from the safetensors header only (never the payload, never pickle; read in plain
    Python: safetensors' own reader imports numpy, which the lite edge agent never loads)."""
    from hammer.learning.lite_policy import safetensors_shapes

    return safetensors_shapes(path)


def check_local_weights(shapes: dict[str, tuple[int, ...]], input_dim: int, env: dict, what: str) -> None:
    """The local policy's first layer takes `input_dim` inputs and its head gives the env's action width."""
    first = shapes.get("actor.layers.0.weight")
    if first is None:
        raise BundleError(f"{what}: no 'actor.layers.0.weight' tensor; fix: export the bundle from a run's final/ policy")
    if first[1] != input_dim:
        raise BundleError(f"{what}: the local policy takes {first[1]} inputs but env {env['name']} "
                          f"(obs_dim {env['obs_dim']}) with this variant gives {input_dim}; fix: serve it on the "
                          "env it was trained on")
    i = max(int(k.split(".")[2]) for k in shapes if k.startswith("actor.layers.") and k.endswith(".weight"))
    out = shapes[f"actor.layers.{i}.weight"][0]
    if out != env["action_dim"]:
        raise BundleError(f"{what}: the local policy has {out} action outputs, env {env['name']} has "
                          f"action_dim {env['action_dim']}; fix: serve it on the env it was trained on")


def check_central_weights(shapes: dict[str, tuple[int, ...]], central_net: str, n_agents: int, what: str) -> None:
    """The central file holds the network the config names (`central_net`: `head_weight` for concat,
    `layout` for set; docs/wire-format.md) built for the env's N."""
    kind = "set" if "layout" in shapes else "concat" if "head_weight" in shapes else None
    if kind is None:
        raise BundleError(f"{what}: neither 'head_weight' nor 'layout': not a central agent's weights; fix: export "
                          "the bundle from a run's final/ policy")
    if kind != central_net:
        raise BundleError(f"{what}: holds the {kind} central network but the config says central_net={central_net}; "
                          "fix: export the bundle again from the run that trained these weights")
    if kind == "concat" and shapes["head_weight"][0] != n_agents:
        raise BundleError(f"{what}: {shapes['head_weight'][0]} message heads for n_agents {n_agents}; fix: serve it "
                          "on the env it was trained on")


@dataclass(frozen=True)
class Bundle:
    """A checked bundle: its directory and manifest."""

    path: Path
    manifest: dict[str, Any]

    @property
    def policy_dir(self) -> Path:
        """What `RuntimeSettings.policy_dir` takes: the directory holding the safetensors files."""
        return self.path

    @property
    def config_data(self) -> dict[str, Any]:
        return dict(self.manifest["config"])

    @property
    def env_spec_data(self) -> dict[str, Any]:
        return dict(self.manifest["env_spec"])

    def wiring(self):
        """What the variant means for the runners (learning.variant.Wiring), from the manifest alone: no
        RunConfig is built (the edge agent never imports the training config)."""
        from types import SimpleNamespace

        from hammer.learning.variant import Wiring

        c = self.config_data
        return Wiring.from_config(SimpleNamespace(**{k: c[k] for k in ("variant", "central_mode", "n_agents", "msg_dim")},
                                                  msg_dropout=c.get("msg_dropout", 0.0),
                                                  central_net=c.get("central_net", "concat")))

    def config(self, **update: Any):
        """The team's RunConfig (pydantic, no torch), with fields replaced (e.g. episodes, seed)."""
        from hammer.learning.config import build_config

        return build_config({**self.config_data, **update})

    def env_spec(self):
        from hammer.envs.base import EnvSpec

        d = self.env_spec_data
        return EnvSpec(**{**d, "agent_ids": tuple(d["agent_ids"])})

    def check_env(self, spec) -> None:
        """The env a server built (an EnvSpec, or an env_spec.json mapping) must be the one the team was
        trained on (dims the weights fit)."""
        have = {f: spec[f] if isinstance(spec, dict) else getattr(spec, f) for f in SPEC_FIELDS}
        want = {f: self.env_spec_data[f] for f in SPEC_FIELDS}
        bad = [f"{f} {want[f]} (env has {have[f]})" for f in SPEC_FIELDS if have[f] != want[f]]
        if bad:
            raise BundleError(f"{self.path}: the bundle was trained on {', '.join(bad)}; fix: serve it with "
                              "the env id and env_kwargs in its manifest")

    def check_env_here(self, cfg) -> None:
        """The env this machine builds from the served config (`cfg`) must have the dims the weights
        were trained on: an env library of another version may not."""
        from hammer.envs.registry import make_vec_env

        env = make_vec_env(cfg.env, cfg.n_agents, 1, env_kwargs=cfg.env_kwargs or None)
        try:
            self.check_env(env.spec)
        finally:
            env.close()


def export_bundle(run_dir: Path, out: Path, *, force: bool = False, sign: Path | None = None,
                  works_with: tuple[Path, ...] = ()) -> Bundle:
    """Write a bundle of the trained team in `run_dir` (its final/ policy) to `out`; returns it, loaded
    back. `sign`: an ed25519 private key (`hammer keygen`) that signs it (serve/signing.py).
    `works_with`: folders holding a central.safetensors (a bundle, a run's final/ or a served run's
    policies/v<N>/) this team's local policy also works with: a staged rollout pairs the canary's
    local policy with the served central network, and refuses a pair the bundle does not declare
    (its own central network is always declared; serve/push.py)."""
    from hammer.learning.config import build_config

    run_dir, out = Path(run_dir), Path(out)
    cfg_file, final = run_dir / "config.json", run_dir / "final"
    if not cfg_file.is_file():
        raise BundleError(f"{cfg_file} is missing: pass a run directory made by `hammer train` or `hammer up`")
    cfg = build_config(json.loads(cfg_file.read_text()))
    files = [LOCAL, *([CENTRAL] if cfg.wiring.has_central_network else [])]
    for name in files:
        if not (final / name).is_file():
            raise BundleError(f"{final / name} is missing: the run has not finished (final/ is written at its end); "
                              "fix: export a finished run")
    if out.exists() and not force:
        raise BundleError(f"{out} exists; fix: choose another --out or pass --force to replace it")
    env_spec = _env_spec(run_dir, cfg)
    check_local_weights(_weight_shapes(final / LOCAL), cfg.wiring.local_input_dim(env_spec["obs_dim"]), env_spec,
                        str(final / LOCAL))
    summary = _read_json(run_dir / "summary.json")
    runtime = _read_json(run_dir / "runtime.json")
    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for name in files:
        shutil.copyfile(final / name, tmp / name)
    w = cfg.wiring
    manifest = {
        "bundle_format": BUNDLE_FORMAT,
        "schema_version": SCHEMA_VERSION,
        "created_at": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "env": {"id": cfg.env, "kwargs": cfg.env_kwargs or {}},
        "env_spec": env_spec,
        "variant": cfg.variant,
        "central_mode": cfg.central_mode if w.has_central_network else None,
        "central_net": cfg.central_net if w.has_central_network else None,
        "msg_dim": w.msg_dim,
        "local_input_dim": w.local_input_dim(env_spec["obs_dim"]),
        "fallback": {"mode": runtime.get("fallback", "zeros"), "k": runtime.get("fallback_k", 3)},
        "source": {"run": run_dir.name, "path": str(run_dir.resolve()), "seed": cfg.seed,
                   "episodes": summary.get("episodes"),
                   "final_paper_metric_last500": summary.get("final_paper_metric_last500")},
        "config": cfg.model_dump(mode="json"),
        "files": {name: sha256(tmp / name) for name in files},
    }
    if works_with:
        found = [Path(d) / CENTRAL for d in works_with]
        missing = [str(f) for f in found if not f.is_file()]
        if missing:
            shutil.rmtree(tmp, ignore_errors=True)
            raise BundleError(f"--works-with: {', '.join(missing)} missing; fix: name a bundle or policy folder "
                              "holding the central network's weights")
        manifest["works_with_central"] = sorted({sha256(f) for f in found})
    manifest["seal"] = seal(manifest)
    (tmp / MANIFEST).write_text(json.dumps(manifest, indent=1))
    if sign is not None:
        from hammer.serve.signing import sign_manifest

        sign_manifest(tmp / MANIFEST, sign)
    if out.exists():
        shutil.rmtree(out)
    tmp.rename(out)
    return load_bundle(out)


def _read_json(path: Path) -> dict:
    return json.loads(path.read_text()) if path.is_file() else {}


def _env_spec(run_dir: Path, cfg) -> dict:
    """env_spec.json of a `hammer up` run; a `hammer train` run has none, so the env is built once."""
    from dataclasses import asdict

    d = _read_json(run_dir / "env_spec.json")
    if not d:
        from hammer.envs.registry import make_vec_env

        env = make_vec_env(cfg.env, cfg.n_agents, 1, env_kwargs=cfg.env_kwargs or None)
        d = asdict(env.spec)
        env.close()
    d["agent_ids"] = list(d["agent_ids"])
    return d


def load_bundle(path: Path, check_config: bool = True, trust: tuple[Path, ...] | list[Path] = ()) -> Bundle:
    """Read and check a bundle: format, wire schema, the manifest's seal, every file's sha256, the
    weights against the env's dims. check_config=False: the full RunConfig is not validated (the edge
    agent reads only the wiring). `trust`: public keys (`hammer keygen`'s NAME.pub), one of which must
    have signed the manifest, checked before anything else is read from it."""
    path = Path(path)
    mf = path / MANIFEST
    if not mf.is_file():
        raise BundleError(f"{mf} is missing: pass a directory made by `hammer export RUN --out BUNDLE`")
    if trust:
        from hammer.serve.signing import verify_manifest

        verify_manifest(mf, list(trust))
    try:
        m = json.loads(mf.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise BundleError(f"{mf}: not valid JSON ({e}); fix: export the bundle again") from None
    if not isinstance(m, dict):
        raise BundleError(f"{mf}: expected a JSON object; fix: export the bundle again")
    fmt = m.get("bundle_format")
    if not isinstance(fmt, int) or fmt < 1:
        raise BundleError(f"{mf}: bundle_format {fmt!r} is not a format number; fix: export the bundle again")
    if fmt > BUNDLE_FORMAT:
        raise BundleError(f"{mf}: bundle_format {fmt} is newer than this hammer reads ({BUNDLE_FORMAT}); "
                          "fix: upgrade hammer on this machine")
    if m.get("schema_version") != SCHEMA_VERSION:
        raise BundleError(f"{mf}: schema_version {m.get('schema_version')!r}, this hammer speaks {SCHEMA_VERSION}; "
                          "fix: run a hammer of the same wire schema, or export the team again")
    missing = [k for k in ("env_spec", "config", "files", "variant", "msg_dim", "local_input_dim") if k not in m]
    if missing:
        raise BundleError(f"{mf}: no {', '.join(missing)}; fix: export the bundle again")
    check_manifest(m, mf)
    if fmt >= 2 and m.get("seal") != seal(m):
        raise BundleError(f"{mf}: the manifest changed after export (its seal {str(m.get('seal'))[:16]}... does not "
                          "match its fields: a hand edit or a corrupted copy); fix: copy the bundle again, or export "
                          "it again with the values you want (serve-time choices are options of hammer serve)")
    files = m["files"]
    if LOCAL not in files or (m.get("central_mode") is not None and CENTRAL not in files):
        raise BundleError(f"{mf}: files lacks the policy this variant needs; fix: export the bundle again")
    for name, digest in files.items():
        f = path / name
        if Path(name).name != name or not f.is_file():
            raise BundleError(f"{path}: {name} is missing; fix: copy the whole bundle directory")
        if sha256(f) != digest:
            raise BundleError(f"{f}: sha256 differs from the manifest (corrupted or changed); "
                              "fix: copy the bundle again or export it again")
    shapes = _checked_shapes(path / LOCAL)
    try:
        cfg = Bundle(path, m).config() if check_config else None  # an edge agent never builds the RunConfig
        wiring = cfg.wiring if cfg is not None else Bundle(path, m).wiring()
    except (ValueError, KeyError, TypeError) as e:
        raise BundleError(f"{mf}: config: {' '.join(str(e).split())[:300]}; fix: export the bundle again") from None
    check_local_weights(shapes, wiring.local_input_dim(int(m["env_spec"]["obs_dim"])), m["env_spec"], str(path / LOCAL))
    if wiring.has_central_network and cfg is not None:  # the central weights: checked where they are served
        check_central_weights(_checked_shapes(path / CENTRAL), cfg.central_net, wiring.n_agents, str(path / CENTRAL))
    return Bundle(path, m)


def _checked_shapes(path: Path) -> dict[str, tuple[int, ...]]:
    try:
        return _weight_shapes(path)
    except Exception as e:  # noqa: BLE001 - a malformed header: say so in one line
        raise BundleError(f"{path}: not a safetensors file ({e})") from None


def is_bundle(path: Path) -> bool:
    return (Path(path) / MANIFEST).is_file()
