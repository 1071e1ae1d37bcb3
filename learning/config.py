"""The run configuration: one strict pydantic model for every knob of a training run.

Why strict: a typo in a sweep (`--set gama=0.9`) must fail loudly instead of silently training with
the default. Every error names the field and says how to fix it (`ConfigError`).

Sources are merged in this order (later wins): model defaults < preset < YAML file < `--set k=v`.
"""

from __future__ import annotations

import copy
import difflib
from pathlib import Path
from typing import Any, Literal

import yaml
from hammer.learning.presets import PRESETS
from hammer.learning.variant import Wiring
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SerializerFunctionWrapHandler,
    ValidationError,
    model_serializer,
    model_validator,
)

Variant = Literal["hammer", "il", "random", "centralized"]
CentralMode = Literal["rl", "backprop"]
CentralNet = Literal["concat", "set"]


# Fields a dump (config.json, checkpoints) leaves out while they hold this default, and that a
# config without them means: added after runs were archived, they change no float32 run's files.
OMITTED_DEFAULTS: dict[str, Any] = {"precision": "fp32"}


class ConfigError(ValueError):
    """A bad configuration value; the message is one line naming the field and the fix."""


class RunConfig(BaseModel):
    """Everything that determines a training run (together with the code version)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    # --- environment -------------------------------------------------------------------------
    env: str = Field("cn", description="registry name: cn, cn-mpe2, mw or module:factory")
    n_agents: int = Field(3, ge=1, description="number of local agents N")
    env_kwargs: dict[str, Any] = Field(default_factory=dict, description="extra env constructor kwargs")
    env_adapters: list[str] = Field(
        default_factory=list, description="PettingZoo adapters (envs.adapters): flatten, one_hot, pad, agent_id, gray, "
                                          "resize:WxH; `hammer envs check ENV` says which an env needs")
    env_workers: int = Field(0, ge=0, description="env slices stepped in parallel processes (0 = in-process)")
    env_parent_slice: bool = Field(
        True, description="with env_workers=W: this process steps one slice itself (W-1 subprocesses) "
                          "instead of idling while W subprocesses step")
    num_envs: int = Field(16, ge=1, description="K env copies stepped as one batch")

    # --- method ------------------------------------------------------------------------------
    variant: Variant = Field("hammer", description="hammer | il | random | centralized")
    central_mode: CentralMode = Field("rl", description="how the central agent learns: rl | backprop")
    central_net: CentralNet = Field(
        "concat", description="the central network: concat (the paper's: an MLP over o_1 ⊕ … ⊕ o_N ⊕ previous "
                              "actions, one head per agent; grows with N²) | set (a per-agent encoder shared by "
                              "all agents + attention across them: permutation-invariant, grows with N)")
    msg_dim: int = Field(4, ge=0, description="message length M (used by hammer and random)")
    use_prev_actions: bool = Field(True, description="global state includes every agent's previous action")
    msg_std: float = Field(0.5, gt=0, description="std of the Gaussian message policy (rl mode)")
    msg_dropout: float = Field(0.0, ge=0, le=1, description="prob. of zeroing each message in training")
    missing_prob: float = Field(
        0.0, ge=0, lt=1, description="training only: the chance that the central agent sees a robot as missing "
                                     "for a window of missing_window vector steps (its observation and previous "
                                     "action zeroed in the global state: a fleet's missing rule, docs/fleet.md)")
    missing_window: int = Field(20, ge=1, description="vector steps a simulated absence (missing_prob) lasts")
    site_missing_prob: float = Field(
        0.0, ge=0, lt=1, description="training only, an env with central-only columns (rware): the chance that the "
                                     "central agent's site feed is absent for a window of missing_window vector "
                                     "steps (those columns zeroed in every row of its state: a fleet's silent "
                                     "rule for the feed, docs/fleet.md)")

    # --- PPO ---------------------------------------------------------------------------------
    rollout_steps: int = Field(50, ge=1, description="vector steps T per update")
    gamma: float = Field(0.95, gt=0, le=1)
    gae_lambda: float = Field(0.95, ge=0, le=1)
    clip: float = Field(0.2, gt=0, lt=1, description="PPO ratio clip epsilon")
    lr_central: float = Field(3e-4, gt=0, lt=1)
    lr_local: float = Field(3e-4, gt=0, lt=1)
    epochs: int = Field(8, ge=1)
    minibatches: int = Field(4, ge=1)
    ent_coef: float = Field(0.01, ge=0)
    vf_coef: float = Field(0.5, ge=0)
    max_grad_norm: float = Field(0.5, gt=0)
    norm_adv: bool = True

    # --- networks ----------------------------------------------------------------------------
    actor_hidden: list[int] = Field(default_factory=lambda: [64, 64])
    critic_hidden: list[int] = Field(default_factory=lambda: [64, 32])
    central_hidden: list[int] = Field(default_factory=lambda: [64, 64])
    log_std_init: float = Field(-0.5, description="initial log-std of the Gaussian local policy")
    obs_conv: list[int] = Field(
        default_factory=list, description="[H, W, C]: the first H*W*C observation values are an image (HWC, e.g. "
                                          "[32, 32, 1] from env_adapters [gray, resize:32x32, flatten]); the local "
                                          "networks read it through a small conv encoder. Empty: MLP only")

    # --- run ---------------------------------------------------------------------------------
    episodes: int = Field(30_000, ge=1, description="budget in finished episodes")
    seed: int = Field(0, ge=0, lt=2**31)
    torch_threads: int = Field(1, ge=1, description="torch intra-op threads (small nets: 1 is fastest)")
    compile: bool = Field(
        False, description="torch.compile each PPO minibatch step (losses, gradients, clip, Adam) into one "
                           "graph: faster updates once compiled (first compile takes a while; `hammer bench` measures "
                           "both); float rounding differs from eager")
    compile_scope: Literal["step", "epoch"] = Field(
        "step", description="with compile=true, what one graph holds: `step`, one minibatch step; `epoch`, a "
                            "whole epoch (its shuffle and every minibatch step: one call per epoch, updates ~15-25% "
                            "faster, but ~4x the compile; pays in long runs and benchmarks). Solo runs, seed batches "
                            "(`--seeds`) and `hammer up`'s learner")
    device: str = Field(
        "cpu", pattern=r"^(cpu|cuda(:[0-9]+)?)$",
        description="where the networks, their optimiser state and the PPO update live: cpu | cuda | cuda:N. "
                    "The envs and the acting draws stay numpy on the host (a host-device round trip around each "
                    "acting forward pass); `--resume RUN --set device=...` moves a run (docs/learning.md)")
    precision: Literal["fp32", "bf16"] = Field(
        "fp32", description="the PPO update's forward passes: fp32, or bf16 (torch.autocast to bfloat16; weights, "
                            "gradients, Adam state and acting stay float32). bf16 only where the hardware has native "
                            "bfloat16 matmuls (AVX512_BF16/AMX CPUs, bf16 GPUs), refused elsewhere; results differ "
                            "from fp32 (docs/fast-envs.md)")
    out: str = Field("runs", description="root directory for run directories")
    checkpoint_every: int = Field(50, ge=1, description="updates between checkpoints")

    @model_validator(mode="after")
    def _consistent(self) -> RunConfig:
        for name in ("actor_hidden", "critic_hidden", "central_hidden"):
            sizes = getattr(self, name)
            if not sizes or any(s < 1 for s in sizes):
                raise ValueError(f"{name}: needs at least one positive layer size, e.g. [64, 64]")
        if self.wiring.uses_central and self.msg_dim < 1:
            raise ValueError(f"msg_dim: variant {self.variant} needs msg_dim >= 1 (or use variant il)")
        if self.central_net != "concat" and not self.wiring.has_central_network:
            raise ValueError(f"central_net: variant {self.variant} has no central network, so central_net="
                             f"{self.central_net} would change nothing")
        if self.obs_conv and (len(self.obs_conv) != 3 or min(self.obs_conv) < 1):
            raise ValueError("obs_conv: needs [H, W, C], three positive sizes, e.g. [32, 32, 1]")
        if self.obs_conv and self.wiring.joint_obs:
            raise ValueError("obs_conv: not with variant centralized (its local input is every agent's observation)")
        if self.minibatches > self.rollout_steps * self.num_envs:
            raise ValueError("minibatches: must be <= rollout_steps * num_envs")
        return self

    @model_serializer(mode="wrap")
    def _dump(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        # Fields written only when set (OMITTED_DEFAULTS): a float32 run's config.json, checkpoint
        # metadata and sweep snapshots are byte for byte what they were before the field existed.
        data = handler(self)
        for name, default in OMITTED_DEFAULTS.items():
            if data.get(name) == default:
                del data[name]
        return data

    @property
    def effective_msg_dim(self) -> int:
        """Message length the local agents actually receive (0 for il and centralized)."""
        return self.wiring.msg_dim

    @property
    def wiring(self) -> Wiring:
        """What the variant and central mode mean for every runner (`learning.variant`)."""
        return Wiring.from_config(self)

    def run_name(self) -> str:
        return f"{self.env.replace(':', '_')}{self.n_agents}-{self.wiring.label}-s{self.seed}"


_FIXES = {
    "variant": "use one of hammer, il, random, centralized",
    "central_mode": "use rl or backprop",
    "central_net": ("use concat (the paper's network) or set (per-agent encoder + attention) with variant hammer, "
                    "e.g. --set central_net=set; drop it for variants without a central network"),
    "gamma": "use a discount in (0, 1], e.g. gamma=0.95",
    "gae_lambda": "use a value in [0, 1], e.g. gae_lambda=0.95",
    "clip": "use a clip epsilon in (0, 1), e.g. clip=0.2",
    "msg_dropout": "use a probability in [0, 1]",
    "missing_prob": "use a probability in [0, 1), e.g. --set missing_prob=0.1 (0: no simulated absences)",
    "missing_window": "use a number of vector steps >= 1, e.g. --set missing_window=20",
    "site_missing_prob": "use a probability in [0, 1), e.g. --set site_missing_prob=0.1 (0: the site feed always there)",
    "episodes": "use a budget >= 1, e.g. --episodes 2000 (or --set episodes=2000)",
    "seed": "use an int, e.g. --seed 1 (or --set seed=1)",
    "device": "use cpu, cuda or cuda:N, e.g. --set device=cuda",
    "precision": "use fp32 or bf16, e.g. --set precision=bf16",
}


def fields_help() -> str:
    """Every RunConfig field with its default and description, one paragraph each: the second half of
    `hammer train --help` and `hammer up --help` (generated here, so it cannot drift from the model)."""
    out = []
    for name, f in RunConfig.model_fields.items():
        default = f.get_default(call_default_factory=True)
        out.append(f"{name} = {default!r}: {f.description or ''}".rstrip(": "))
    return "\n\n".join(out)


def _format_error(err: ValidationError) -> str:
    parts = []
    for e in err.errors():
        field = ".".join(str(x) for x in e["loc"]) or "config"
        if e["type"] == "extra_forbidden":
            close = difflib.get_close_matches(str(e["loc"][0]), RunConfig.model_fields, n=1)
            hint = f"did you mean '{close[0]}'?" if close else "see `hammer train --help` for the fields"
            parts.append(f"config field '{field}': unknown field; fix: remove it ({hint})")
            continue
        msg = e["msg"].removeprefix("Value error, ")
        if not e["loc"] and ":" in msg:  # model-level checks name their field first
            field, msg = (s.strip() for s in msg.split(":", 1))
        got = f" (got {e['input']!r})" if e["loc"] and "input" in e else ""
        fix = _FIXES.get(field, f"set a valid value with --set {field}=...")
        parts.append(f"config field '{field}': {msg}{got}; fix: {fix}")
    return "; ".join(parts)


def build_config(data: dict[str, Any]) -> RunConfig:
    """Validate a merged dict into a RunConfig, raising a one-line `ConfigError`."""
    try:
        return RunConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(_format_error(err)) from None


def parse_override(item: str) -> tuple[list[str], Any]:
    """`key=value` or `env_kwargs.key=value`; the value is parsed as YAML (so 1e-4, true, [64,64])."""
    if "=" not in item:
        raise ConfigError(f"override '{item}': expected key=value, e.g. --set gamma=0.95")
    key, raw = item.split("=", 1)
    key = key.strip().replace("-", "_")
    if not key:
        raise ConfigError(f"override '{item}': empty key; fix: write key=value")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError:
        value = raw
    return key.split("."), value


def yaml_error_text(err: Exception) -> str:
    """Where and what a YAML error is, for a one-line message: ', line 3, column 10: invalid YAML (expected
    ',' or ']', but got '<scalar>')' (lines and columns from 1, as an editor counts)."""
    mark = getattr(err, "problem_mark", None) or getattr(err, "context_mark", None)
    where = f", line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    what = " ".join(str(getattr(err, "problem", None) or err.__class__.__name__).split())
    return f"{where}: invalid YAML ({what})"


def load_yaml(path: str | Path) -> dict[str, Any]:
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"config file '{p}': not found; fix: pass an existing YAML file to --config")
    try:
        data = yaml.safe_load(p.read_text()) or {}
    except yaml.YAMLError as err:
        raise ConfigError(f"config file '{p}'{yaml_error_text(err)}; fix the syntax there") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config file '{p}': top level must be a mapping of field: value")
    return data


def preset_dict(name: str) -> dict[str, Any]:
    """A copy of a preset's fields (so callers may mutate it)."""
    if name not in PRESETS:
        raise ConfigError(f"preset '{name}': unknown; fix: use one of {', '.join(PRESETS)}")
    d = dict(PRESETS[name])
    d["env_kwargs"] = dict(d.get("env_kwargs", {}))
    return d


def _merge(data: dict[str, Any], layer: dict[str, Any]) -> None:
    """`layer` over `data`, mapping into mapping: a YAML `env_kwargs: {n_walkers: 3}` over the mw3
    preset changes n_walkers and keeps the preset's other env_kwargs, as `--set env_kwargs.n_walkers=3` does."""
    for key, value in layer.items():
        if isinstance(value, dict) and isinstance(data.get(key), dict):
            data[key] = copy.deepcopy(data[key])
            _merge(data[key], value)
        else:
            data[key] = value


def merge_config(
    preset: str | None = None,
    file: str | Path | None = None,
    overrides: list[str] | None = None,
    extra: dict[str, Any] | None = None,
    base: dict[str, Any] | None = None,
) -> RunConfig:
    """defaults < `base` (a run's own config, for branches) < preset < YAML file < `extra`
    (explicit CLI flags) < `--set` overrides."""
    data: dict[str, Any] = copy.deepcopy(base) if base else {}
    if preset:
        data.update(preset_dict(preset))
    if file:
        _merge(data, load_yaml(file))
    _merge(data, {k: v for k, v in (extra or {}).items() if v is not None})
    for item in overrides or []:
        keys, value = parse_override(item)
        node = data
        for k in keys[:-1]:
            node = node.setdefault(k, {})
            if not isinstance(node, dict):
                raise ConfigError(f"override '{item}': '{k}' is not a mapping")
        node[keys[-1]] = value
    return build_config(data)


# Fields that choose how a result is computed, never the result: the numpy warehouse equals rware
# step for step (tests/test_rware_exact.py), so a run on either implementation is the same run.
RESULT_NEUTRAL = frozenset({"env_kwargs.impl"})


def config_changes(ours: dict[str, Any], reference: dict[str, Any],
                   ignore: frozenset[str] | set[str] = frozenset()) -> dict[str, Any]:
    """Every field where two resolved configs (`model_dump(mode="json")`) differ, as dotted key ->
    our value, sorted by key: `lr_local`, `env_kwargs.observe_others`. Nested mappings are compared
    key by key, and a key either side lacks counts as a change (ours `None` if we lack it).
    Top-level fields the reference lacks (renamed or removed since `ours` was written) and the
    `ignore`d ones and the `RESULT_NEUTRAL` ones (dotted) are skipped; an `OMITTED_DEFAULTS` field
    either side lacks holds its default. Shared by sweep snapshots (is this the same run?) and reports
    (which runs pool as seeds of one setting?), so both agree on what "differs" means."""

    ours, reference = {**OMITTED_DEFAULTS, **ours}, {**OMITTED_DEFAULTS, **reference}

    def diff(a: dict[str, Any], b: dict[str, Any], prefix: str) -> dict[str, Any]:
        out: dict[str, Any] = {}
        keys = set(a) if not prefix else set(a) | set(b)
        for key in sorted(keys):
            if not prefix and (key in ignore or key not in b):
                continue
            if f"{prefix}{key}" in RESULT_NEUTRAL:
                continue
            x, y = a.get(key), b.get(key)
            if isinstance(x, dict) and isinstance(y, dict):
                out.update(diff(x, y, f"{prefix}{key}."))
            elif x != y or (key in a) != (key in b):
                out[f"{prefix}{key}"] = x
        return out

    return diff(ours, reference, "")


def save_yaml(cfg: RunConfig, path: str | Path) -> None:
    Path(path).write_text(yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False))
