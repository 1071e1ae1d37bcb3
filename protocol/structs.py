"""The base of hammer's settings (runtime, transport, faults): msgspec Structs, so a torch-free edge
agent, which loads msgspec for the wire anyway, loads no pydantic (the training config stays pydantic).

A settings Struct is validated however it is made:

* `parse(Cls, mapping)`: a run file, a config section, `--runtime` / `--fault` items; lax, numbers
  and booleans also from their strings (`drop=0.2`), an int from an integral float; nested mappings
  become the nested Structs;
* `Cls(field=...)`: the same checks, run on the built instance (msgspec's constructor checks none).

Bounds are `Meta(ge=..., le=...)` on the annotation; rules over a field's value or several fields are
`check()`, which raises ValueError naming the field and the fix. A field a caller may leave to someone
else (a Zenoh config file, a fleet's defaults) defaults to None, so "not given" is that None.
Every refusal is a `SettingsError`: one line, `Model: field: what is wrong`.
"""

from __future__ import annotations

import contextvars
import re
import typing
from typing import Any, TypeVar

import msgspec

__all__ = ["Meta", "Settings", "SettingsError", "default_of", "dump", "field_names", "parse", "replace"]

Meta = msgspec.Meta
S = TypeVar("S", bound="Settings")

# Set while msgspec builds a Struct from a mapping: the fields are then already converted and bounded,
# and the built instance runs only its own check().
_PARSING: contextvars.ContextVar[bool] = contextvars.ContextVar("hammer_settings_parsing", default=False)


class SettingsError(ValueError):
    """A settings input refused: `model`, `field` (dotted path, "" for the whole), `msg`, `kind`
    (`unknown`, `missing` or `invalid`) and `value` (the input of a top-level field, if known)."""

    def __init__(self, model: str, field: str, msg: str, kind: str = "invalid", value: Any = None) -> None:
        self.model, self.field, self.msg, self.kind, self.value = model, field, msg, kind, value
        super().__init__(f"{model}: {field + ': ' if field else ''}{msg}")

    def __reduce__(self) -> tuple:  # picklable (a worker's error crossing a process boundary)
        return type(self), (self.model, self.field, self.msg, self.kind, self.value)


class Settings(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """Base of a settings Struct (see the module doc). Subclasses define fields and, if needed, check()."""

    def __post_init__(self) -> None:
        if _PARSING.get():
            self.check()
            return
        # Built by keywords: convert and bound each value as a mapping would be (check() runs in there).
        new = parse(type(self), {f: getattr(self, f) for f in self.__struct_fields__})
        for f in self.__struct_fields__:
            setattr(self, f, getattr(new, f))

    def check(self) -> None:
        """Rules beyond one field's type and bounds; raise ValueError naming the field and the fix."""


def parse(cls: type[S], data: Any) -> S:
    """`data` (a mapping, or already a `cls`) as a validated `cls`; SettingsError in one line if refused."""
    if isinstance(data, cls):
        return data
    token = _PARSING.set(True)
    try:
        return msgspec.convert(data, cls, strict=False)
    except msgspec.ValidationError as e:
        raise _error(cls, str(e), data) from None
    finally:
        _PARSING.reset(token)


def replace(obj: S, **changes: Any) -> S:
    """A copy of `obj` with `changes`, validated like a new one."""
    return msgspec.structs.replace(obj, **changes)


def dump(obj: Settings, exclude: Any = ()) -> dict:
    """`obj` as plain data (nested Structs as dicts), fields in their order, without `exclude`."""
    return {k: v for k, v in msgspec.to_builtins(obj).items() if k not in exclude}


def field_names(cls: type[Settings]) -> tuple[str, ...]:
    return cls.__struct_fields__


def default_of(cls: type[Settings], name: str) -> Any:
    f = next(f for f in msgspec.structs.fields(cls) if f.name == name)
    return f.default_factory() if f.default_factory is not msgspec.NODEFAULT else f.default


_WORDS = {"int": "an integer", "float": "a number", "str": "a string", "bool": "a boolean (true or false)",
          "array": "a list", "object": "a mapping", "null": "null"}
_AT = re.compile(r"(.*?)(?: - at `\$(.*)`)?", re.DOTALL)


def _error(cls: type, text: str, data: Any) -> SettingsError:
    """msgspec's `what - at `$.path`` as hammer's wording: the field first, then what it should be."""
    msg, path = _AT.fullmatch(text).groups()
    field = (path or "").lstrip(".")
    value = data.get(field) if isinstance(data, dict) else None
    if m := re.fullmatch(r"Object contains unknown field `(.+)`", msg):
        return SettingsError(cls.__name__, f"{field}.{m[1]}" if field else m[1], "unknown field", "unknown")
    if m := re.fullmatch(r"Object missing required field `(.+)`", msg):
        return SettingsError(cls.__name__, f"{field}.{m[1]}" if field else m[1], "required, not given", "missing")
    if m := re.fullmatch(r"Expected `(\w+)`(?:, got `(\w+)`)?(?: (.*))?", msg):
        want, got, bound = m.groups()
        msg = f"should be {_WORDS.get(want, want)}{' ' + bound if bound else ''}"
        msg += f", not {_WORDS.get(got, got)}" if got else ""
    elif m := re.fullmatch(r"Invalid enum value (.+)", msg):
        choices = _choices(cls, field)
        msg = f"{m[1]} is not a choice" + (f"; fix: one of {', '.join(map(str, choices))}" if choices else "")
        value = None  # the message shows it
    return SettingsError(cls.__name__, field, msg, "invalid", value)


def _choices(cls: type, field: str) -> tuple:
    """The Literal choices of a top-level field (empty for anything else)."""
    tp = typing.get_type_hints(cls).get(field)
    for t in (tp, *typing.get_args(tp)):
        if typing.get_origin(t) is typing.Literal:
            return typing.get_args(t)
    return ()
