"""Env names -> `VecEnv`: the one entry point (`make_vec_env`) the trainer and the env host call.

Names:
  cn        vectorised cooperative navigation (`envs.spread.VecSimpleSpread`, numpy, all K copies
            in one array program); local_ratio 0.5, 25 steps; observe_others=False hides the
            other agents from each local observation (not in mpe2).
  cn-mpe2   the same task through PettingZoo: mpe2 simple_spread_v3, discrete actions, 25 steps,
            local_ratio 0.5 (the reference the vectorised version is checked against).
  mw        SISL multiwalker_v9 with the paper's settings (individual rewards, fallen walkers
            removed, terrain 200, 500 steps), stepped without PettingZoo's AEC wrappers where that
            is exact (`envs.multiwalker_direct`: terminate_on_fall=True, the paper's setting).
  mw-pettingzoo
            the same env through PettingZoo's parallel wrapper all the way (the reference).
  module:factory
            any PettingZoo parallel env, e.g. `pettingzoo.sisl.pursuit_v4:parallel_env`; env_kwargs
            are passed to the factory and n_agents must match its possible_agents.

`env_kwargs` override the defaults field by field; unknown fields are refused with the list of valid
ones. `workers=0` steps the K copies in this process; `workers>=1` splits them over that many
subprocesses (`envs.workers.SubprocVecEnv`), which rebuild the env from the picklable
`EnvDescription`, never from a pickled env.
"""

from __future__ import annotations

import importlib
import inspect
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from envs.base import VecEnv

log = logging.getLogger(__name__)


class EnvConfigError(ValueError):
    """An env name, a kwarg or a size that the registry cannot build; the message says the fix."""


@dataclass(frozen=True)
class _Entry:
    module: str  # where the parallel-env factory lives
    factory: str
    n_key: str  # the factory's kwarg for the number of agents
    defaults: dict[str, Any]
    signature_of: str  # "module:attr" whose __init__/call signature lists the valid kwargs
    about: str
    wrap: str | None = None  # "module:fn", fn(parallel_env, kwargs) -> the env to use (e.g. a faster exact step)


_MW_DEFAULTS: dict[str, Any] = {
    "position_noise": 1e-3, "angle_noise": 1e-3, "forward_reward": 1.0, "terminate_reward": -100.0,
    "fall_reward": -10.0, "terminate_on_fall": True, "remove_on_fall": True, "terrain_length": 200,
    "shared_reward": False, "max_cycles": 500}

_PETTINGZOO: dict[str, _Entry] = {
    "cn-mpe2": _Entry(
        "mpe2.simple_spread_v3", "parallel_env", "N",
        {"max_cycles": 25, "local_ratio": 0.5, "continuous_actions": False},
        "mpe2.simple_spread.simple_spread:raw_env",
        "cooperative navigation via PettingZoo mpe2 simple_spread_v3 (discrete, 25 steps)",
    ),
    "mw": _Entry(
        "pettingzoo.sisl.multiwalker_v9", "parallel_env", "n_walkers", _MW_DEFAULTS,
        "pettingzoo.sisl.multiwalker.multiwalker_base:MultiWalkerEnv",
        "SISL multiwalker_v9, paper settings (continuous, 500 steps, fallen walkers removed)",
        wrap="envs.multiwalker_direct:wrap_if_exact",
    ),
    "mw-pettingzoo": _Entry(
        "pettingzoo.sisl.multiwalker_v9", "parallel_env", "n_walkers", _MW_DEFAULTS,
        "pettingzoo.sisl.multiwalker.multiwalker_base:MultiWalkerEnv",
        "the same multiwalker stepped through PettingZoo's AEC wrappers (the reference for 'mw')",
    ),
}
_CN_DEFAULTS: dict[str, Any] = {"local_ratio": 0.5, "max_steps": 25}
_CN_ABOUT = "cooperative navigation, vectorised numpy (envs.spread.VecSimpleSpread)"


def env_names() -> list[str]:
    """The registered names; any `module:factory` PettingZoo parallel env is accepted as well."""
    return ["cn", *_PETTINGZOO]


def env_descriptions() -> dict[str, str]:
    """One line per registered name, for `hammer envs list` and error messages."""
    return {"cn": _CN_ABOUT, **{n: e.about for n, e in _PETTINGZOO.items()}}


@dataclass(frozen=True)
class EnvDescription:
    """Everything needed to rebuild an env in another process: plain, picklable data only."""

    name: str
    n_agents: int
    env_kwargs: dict[str, Any] = field(default_factory=dict)


# -- helpers ---------------------------------------------------------------------------------------
def _valid_names() -> str:
    return ", ".join(env_names()) + ", or 'module:factory' for any PettingZoo parallel env"


def _import_attr(path: str, what: str) -> Any:
    mod_name, _, attr = path.partition(":")
    try:
        mod = importlib.import_module(mod_name)
    except ImportError as e:
        raise EnvConfigError(f"env {what!r}: cannot import module {mod_name!r} ({e}); valid names: "
                             f"{_valid_names()}") from e
    try:
        return getattr(mod, attr)
    except AttributeError as e:
        raise EnvConfigError(f"env {what!r}: module {mod_name!r} has no attribute {attr!r}; valid names: "
                             f"{_valid_names()}") from e


def _kwarg_names(fn: Callable[..., Any]) -> set[str] | None:
    """Keyword names `fn` accepts, or None when it takes **kwargs (cannot check up front)."""
    target = fn.__init__ if inspect.isclass(fn) else fn
    params = inspect.signature(target).parameters.values()
    if any(p.kind is p.VAR_KEYWORD for p in params):
        return None
    return {p.name for p in params if p.name != "self" and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}


def _check_kwargs(name: str, kwargs: dict[str, Any], valid: set[str] | None, reserved: str | None) -> None:
    if valid is not None:
        unknown = sorted(set(kwargs) - valid)
        if unknown:
            raise EnvConfigError(f"env {name!r}: unknown env_kwargs field {unknown[0]!r}; valid fields: "
                                 f"{', '.join(sorted(valid - {reserved}))}")
    if reserved is not None and reserved in kwargs:
        raise EnvConfigError(f"env {name!r}: env_kwargs field {reserved!r} is set by n_agents; pass "
                             f"n_agents instead of env_kwargs[{reserved!r}]")


def parallel_env_factory(desc: EnvDescription) -> tuple[Callable[[], Any], str, int | None]:
    """(factory of one parallel env, spec name, max_steps or None) for a PettingZoo-backed name.

    Validates the kwargs before anything is built, so a typo fails here with the valid fields.
    """
    kwargs = dict(desc.env_kwargs)
    if desc.name in _PETTINGZOO:
        entry = _PETTINGZOO[desc.name]
        _check_kwargs(desc.name, kwargs, _kwarg_names(_import_attr(entry.signature_of, desc.name)), entry.n_key)
        full = {**entry.defaults, **kwargs, entry.n_key: desc.n_agents}
        fn = _import_attr(f"{entry.module}:{entry.factory}", desc.name)
        if entry.wrap is not None:
            wrap = _import_attr(entry.wrap, desc.name)
            return (lambda: wrap(fn(**full), full)), desc.name, int(full["max_cycles"])
        return (lambda: fn(**full)), desc.name, int(full["max_cycles"])
    if ":" in desc.name:
        fn = _import_attr(desc.name, desc.name)
        if not callable(fn):
            raise EnvConfigError(f"env {desc.name!r}: {desc.name!r} is not callable; name a function that "
                                 "returns a PettingZoo parallel env")
        valid = _kwarg_names(fn)
        if valid is None:  # parallel_wrapper_fn(...) takes **kwargs; the module's raw_env tells the fields
            raw = getattr(importlib.import_module(desc.name.partition(":")[0]), "raw_env", None)
            valid = _kwarg_names(raw) if raw is not None else None
        _check_kwargs(desc.name, kwargs, valid, None)

        def factory() -> Any:
            try:
                return fn(**kwargs)
            except TypeError as e:
                raise EnvConfigError(f"env {desc.name!r}: the factory rejected env_kwargs {sorted(kwargs)}: {e}") from e

        max_cycles = kwargs.get("max_cycles")
        return factory, desc.name, (int(max_cycles) if max_cycles is not None else None)
    raise EnvConfigError(f"env: unknown name {desc.name!r}; valid names: {_valid_names()}")


def build_local(desc: EnvDescription, num_envs: int, index_offset: int = 0) -> VecEnv:
    """The in-process VecEnv for `desc`; also what each worker of `SubprocVecEnv` runs on its slice."""
    from envs.pettingzoo_vec import PettingZooVecEnv

    factory, spec_name, max_steps = parallel_env_factory(desc)
    venv = PettingZooVecEnv(factory, num_envs, name=spec_name, max_steps=max_steps, index_offset=index_offset)
    if venv.spec.n_agents != desc.n_agents:
        venv.close()
        raise EnvConfigError(f"env {desc.name!r}: n_agents={desc.n_agents} but the env has "
                             f"{venv.spec.n_agents} agents {list(venv.spec.agent_ids)}; set n_agents to "
                             f"{venv.spec.n_agents} or pass the env's own size kwarg in env_kwargs")
    return venv


def _make_cn(n_agents: int, num_envs: int, kwargs: dict[str, Any], workers: int) -> VecEnv:
    """The vectorised CN. It steps all K copies in one numpy program, so workers would only add IPC."""
    from envs.spread import VecSimpleSpread

    valid = _kwarg_names(VecSimpleSpread)
    if valid is not None:
        valid -= {"num_envs", "n_agents"}
    _check_kwargs("cn", kwargs, valid, None)
    if workers:
        log.warning("env 'cn' is already vectorised in numpy; workers=%d ignored (runs in-process)", workers)
    try:
        return VecSimpleSpread(num_envs, n_agents, **{**_CN_DEFAULTS, **kwargs})
    except (ValueError, TypeError) as e:  # a bad value (e.g. local_ratio=2): name the env, keep the reason
        raise EnvConfigError(f"env 'cn': {e}") from e


# -- the public entry point ------------------------------------------------------------------------
def make_vec_env(env: str, n_agents: int, num_envs: int, *, env_kwargs: dict[str, Any] | None = None,
                 workers: int = 0, parent_slice: bool = False) -> VecEnv:
    """Build K = num_envs copies of the N = n_agents env `env` (see module docstring for the names).

    Seeding happens in `reset(seed)` (copy k gets seed + k). `workers=0` runs in-process;
    `workers>=1` splits the copies into that many slices stepped in parallel subprocesses, with
    identical results; `parent_slice=True` steps slice 0 in this process instead (W-1 subprocesses;
    workers=1 is then simply in-process).
    """
    if not isinstance(env, str) or not env:
        raise EnvConfigError(f"env: expected a name, got {env!r}; valid names: {_valid_names()}")
    if not isinstance(n_agents, int) or n_agents < 1:
        raise EnvConfigError(f"n_agents: must be an int >= 1, got {n_agents!r}")
    if not isinstance(num_envs, int) or num_envs < 1:
        raise EnvConfigError(f"num_envs: must be an int >= 1, got {num_envs!r}")
    if not isinstance(workers, int) or workers < 0 or workers > num_envs:
        raise EnvConfigError(f"workers: must be an int in [0, num_envs={num_envs}], got {workers!r} "
                             "(0 = in-process)")
    kwargs = dict(env_kwargs or {})
    if env == "cn":
        return _make_cn(n_agents, num_envs, kwargs, workers)
    desc = EnvDescription(env, n_agents, kwargs)
    parallel_env_factory(desc)  # validate the name and kwargs here, before any process starts
    if workers == 0 or (workers == 1 and parent_slice):
        return build_local(desc, num_envs)
    from envs.workers import SubprocVecEnv

    return SubprocVecEnv(desc, num_envs, workers, parent_slice=parent_slice)
