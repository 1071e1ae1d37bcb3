"""The registered env names and how each is built in this process (`envs.registry` has the list).

`parallel_env_factory` checks a PettingZoo-backed name's kwargs before anything is built;
`build_local` builds K copies of it as one in-process batch, which is also what each subprocess
worker of `envs.workers.SubprocVecEnv` runs on its slice; `build_cn` builds the vectorised
cooperative navigation. `envs.registry.make_vec_env` chooses between them.
"""

from __future__ import annotations

import importlib
import inspect
import logging
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from hammer.envs.base import VecEnv
from hammer.envs.description import EnvConfigError, EnvDescription
from hammer.envs.pettingzoo_vec import PettingZooVecEnv

log = logging.getLogger(__name__)


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
        wrap="hammer.envs.multiwalker_direct:wrap_if_exact",
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
    return ["cn", *_PETTINGZOO, "rware"]


def env_descriptions() -> dict[str, str]:
    """One line per registered name (each builds at any N), for `hammer envs list` and error messages."""
    from hammer.envs.rware_vec import ABOUT

    return {"cn": _CN_ABOUT, **{n: e.about for n, e in _PETTINGZOO.items()}, "rware": ABOUT}


def valid_names() -> str:
    """The names as error messages list them."""
    return (", ".join(env_names()) + ", rware-<tiny|small|medium|large>-<N>ag[-easy|-hard], or 'module:factory' "
            "for any PettingZoo parallel env")


# -- helpers ---------------------------------------------------------------------------------------


def _import_attr(path: str, what: str) -> Any:
    mod_name, _, attr = path.partition(":")
    if os.getcwd() not in sys.path:  # a user's module next to their config, as `python -m` finds it (appended:
        sys.path.append(os.getcwd())  # never shadows an installed package)
    try:
        mod = importlib.import_module(mod_name)
    except ImportError as e:
        raise EnvConfigError(f"env {what!r}: cannot import module {mod_name!r} ({e}); valid names: "
                             f"{valid_names()}") from e
    try:
        return getattr(mod, attr)
    except AttributeError as e:
        raise EnvConfigError(f"env {what!r}: module {mod_name!r} has no attribute {attr!r}; valid names: "
                             f"{valid_names()}") from e


def _kwarg_names(fn: Callable[..., Any]) -> set[str] | None:
    """Keyword names `fn` accepts, or None when it takes **kwargs (cannot check up front)."""
    target = fn.__init__ if inspect.isclass(fn) else fn
    params = inspect.signature(target).parameters.values()
    if any(p.kind is p.VAR_KEYWORD for p in params):
        return None
    return {p.name for p in params if p.name != "self" and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}


def _valid_from_type_error(err: TypeError) -> set[str] | None:
    """The keywords of the callable a `TypeError` names ("X.__init__() got an unexpected keyword
    argument"), looked up in the frame that called it: factories behind **kwargs (multiwalker's
    raw_env passes them on to MultiWalkerEnv) cannot be checked up front, but can name the fields."""
    import re

    m = re.match(r"([\w.]+)\(\) got an unexpected keyword argument", str(err))
    tb = err.__traceback__
    if m is None or tb is None:
        return None
    while tb.tb_next is not None:
        tb = tb.tb_next
    parts = [p for p in m.group(1).split(".") if p != "__init__"]
    names = {**tb.tb_frame.f_globals, **tb.tb_frame.f_locals}  # by name, or by qualname when imported "as"
    obj = names.get(parts[0]) or next((v for v in names.values() if getattr(v, "__qualname__", None) == parts[0]),
                                      None)
    for p in parts[1:]:
        obj = getattr(obj, p, None)
    try:
        return _kwarg_names(obj) if callable(obj) else None
    except (TypeError, ValueError):
        return None


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
            return _adapted(lambda: wrap(fn(**full), full), desc), desc.name, int(full["max_cycles"])
        return _adapted(lambda: fn(**full), desc), desc.name, int(full["max_cycles"])
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
                valid_here = _valid_from_type_error(e)
                hint = f"; valid fields: {', '.join(sorted(valid_here))}" if valid_here else ""
                raise EnvConfigError(f"env {desc.name!r}: the factory rejected env_kwargs {sorted(kwargs)}: {e}"
                                     f"{hint}") from e

        max_cycles = kwargs.get("max_cycles")
        return _adapted(factory, desc), desc.name, (int(max_cycles) if max_cycles is not None else None)
    raise EnvConfigError(f"env: unknown name {desc.name!r}; valid names: {valid_names()}")


def _adapted(factory: Callable[[], Any], desc: EnvDescription) -> Callable[[], Any]:
    if not desc.adapters:
        return factory
    from hammer.envs.adapters import apply_adapters

    return lambda: apply_adapters(factory(), desc.adapters)


def build_local(desc: EnvDescription, num_envs: int, index_offset: int = 0) -> VecEnv:
    """The in-process VecEnv for `desc`; also what each worker of `SubprocVecEnv` runs on its slice."""
    from hammer.envs.rware_vec import RwareVecEnv, installed_settings, is_rware

    if is_rware(desc.name):  # two implementations of the same warehouse (env_kwargs.impl)
        settings = installed_settings(desc)
        if settings.impl == "numpy":
            from hammer.envs.rware_numpy import NumpyRwareVecEnv

            return NumpyRwareVecEnv(settings, num_envs, name=desc.name, index_offset=index_offset)
        return RwareVecEnv(settings, num_envs, name=desc.name, index_offset=index_offset)
    factory, spec_name, max_steps = parallel_env_factory(desc)
    venv = PettingZooVecEnv(factory, num_envs, name=spec_name, max_steps=max_steps, index_offset=index_offset)
    if venv.spec.n_agents != desc.n_agents:
        venv.close()
        raise EnvConfigError(f"env {desc.name!r}: n_agents={desc.n_agents} but the env has "
                             f"{venv.spec.n_agents} agents {list(venv.spec.agent_ids)}; set n_agents to "
                             f"{venv.spec.n_agents} or pass the env's own size kwarg in env_kwargs")
    return venv


def build_cn(n_agents: int, num_envs: int, kwargs: dict[str, Any], workers: int) -> VecEnv:
    """The vectorised CN. It steps all K copies in one numpy program, so workers would only add IPC."""
    from hammer.envs.spread import VecSimpleSpread

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

