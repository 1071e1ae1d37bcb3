"""The config models of the edge path without pydantic: a small base offering the part of pydantic's
API hammer's settings use, so a torch-free edge agent loads neither pydantic nor pydantic-core.

What it covers, in pydantic's spelling, so a model reads (and merges) as a pydantic one would:

* fields from the class annotations, `Field(default, default_factory=, ge=, gt=, le=, lt=, description=)`
  or a plain default; `ConfigDict(extra="forbid")` refuses unknown keys;
* types: `int`, `float`, `bool`, `str`, `Path`, `dict`, `list[X]`, `X | None`, `Literal[...]`, a nested
  `Model` (from a dict or an instance), any other class by isinstance; lax like pydantic's: numbers and
  booleans also from their strings (`--fault drop=0.2`, YAML, JSON), an int field from an integral
  float; a bool is no number here (pydantic took `True` as 1);
* `@field_validator("a", "b")` (classmethod: value in, value out) and `@model_validator(mode="after")`
  (method: runs on the built instance, in the class's order, after every field is valid);
* `model_validate`, `model_dump(exclude=, exclude_unset=)`, `model_dump_json(indent=, exclude=)`,
  `model_copy(update=)` (no validation, like pydantic's), `model_fields` (name -> `FieldInfo`),
  `model_fields_set`;
* `ValidationError(ValueError)` with pydantic's `errors()` rows (`type`, `loc`, `msg`, `input`) and
  its wording for type and bound errors ("Input should be greater than 0"), as one line.

Why not pydantic: on the edge agent pydantic + pydantic-core cost more memory and start time than
everything else these four small settings models need (docs/deploy.md "Footprint"). Why not msgspec Structs: they cannot say which
fields a caller set (`model_fields_set`: which transport settings override a Zenoh config file,
which runtime.json keys were written), and their errors would need rewording to name the field and
the fix; this module imports nothing beyond the standard library and keeps pydantic's spelling of
the models' definitions.
"""

from __future__ import annotations

import inspect
import json
import types
import typing
from pathlib import Path
from typing import Any, ClassVar, Literal, Union

__all__ = ["ConfigDict", "Field", "FieldInfo", "Model", "ValidationError", "field_validator", "model_validator"]

_REQUIRED: Any = object()


class ValidationError(ValueError):
    """A model's input refused: `errors()` is one row per problem, as pydantic's (type, loc, msg, input)."""

    def __init__(self, title: str, errors: list[dict]) -> None:
        self.title = title
        self._errors = errors
        super().__init__(f"{title}: " + "; ".join(
            f"{'.'.join(map(str, e['loc']))}: {e['msg']}" if e["loc"] else e["msg"] for e in errors))

    def __reduce__(self) -> tuple:  # picklable (a worker's error crossing a process boundary)
        return type(self), (self.title, self._errors)

    def errors(self, include_url: bool = False) -> list[dict]:
        return [dict(e) for e in self._errors]

    def error_count(self) -> int:
        return len(self._errors)


class _Bad(Exception):
    """One field's value refused (inside this module only): rows with locations relative to it."""

    def __init__(self, rows: list[dict]) -> None:
        self.rows = rows


def _bad(kind: str, msg: str, value: Any) -> _Bad:
    return _Bad([{"type": kind, "loc": (), "msg": msg, "input": value}])


def ConfigDict(**kw: Any) -> dict:
    return dict(kw)


class FieldInfo:
    """One field: its default (or factory), bounds and description."""

    __slots__ = ("annotation", "convert", "default", "default_factory", "description", "ge", "gt", "le", "lt")

    def __init__(self, default: Any = _REQUIRED, *, default_factory: Any = None, ge: Any = None, gt: Any = None,
                 le: Any = None, lt: Any = None, description: str | None = None) -> None:
        self.default, self.default_factory = default, default_factory
        self.ge, self.gt, self.le, self.lt = ge, gt, le, lt
        self.description = description
        self.annotation: Any = None
        self.convert: Any = None

    def is_required(self) -> bool:
        return self.default is _REQUIRED and self.default_factory is None

    def get_default(self, call_default_factory: bool = False) -> Any:
        if self.default_factory is not None:
            return self.default_factory() if call_default_factory else None
        return None if self.default is _REQUIRED else self.default

    def check_bounds(self, v: Any, given: Any) -> None:
        for bound, ok, words, kind in ((self.gt, lambda b: v > b, "greater than", "greater_than"),
                                       (self.ge, lambda b: v >= b, "greater than or equal to", "greater_than_equal"),
                                       (self.lt, lambda b: v < b, "less than", "less_than"),
                                       (self.le, lambda b: v <= b, "less than or equal to", "less_than_equal")):
            if bound is not None and not ok(bound):
                raise _bad(kind, f"Input should be {words} {bound}", given)


def Field(default: Any = _REQUIRED, **kw: Any) -> Any:
    return FieldInfo(default, **kw)


class _FieldValidator:
    def __init__(self, func: Any, names: tuple[str, ...]) -> None:
        self.func, self.names = func, names


class _ModelValidator:
    def __init__(self, func: Any) -> None:
        self.func = func


def field_validator(*names: str) -> Any:
    """`@field_validator("a", "b")` over a classmethod taking the converted value, returning it (or raising ValueError)."""
    return lambda func: _FieldValidator(func, names)


def model_validator(*, mode: str) -> Any:
    """`@model_validator(mode="after")` over a method of the built instance (raises ValueError)."""
    if mode != "after":
        raise NotImplementedError("only mode='after' model validators")
    return _ModelValidator


# ---- converters: annotation -> function(value) -> value (raises _Bad) --------------------------------

_TRUE = {"true", "1", "yes", "y", "on", "t"}
_FALSE = {"false", "0", "no", "n", "off", "f"}


def _to_int(v: Any) -> int:
    if isinstance(v, bool):
        raise _bad("int_type", "Input should be a valid integer, not a boolean", v)
    if isinstance(v, int):
        return int(v)
    if isinstance(v, float):
        if v.is_integer():
            return int(v)
        raise _bad("int_from_float", "Input should be a valid integer, got a number with a fractional part", v)
    if isinstance(v, str):
        try:
            return int(v.strip())
        except ValueError:
            raise _bad("int_parsing", "Input should be a valid integer, unable to parse string as an integer",
                       v) from None
    raise _bad("int_type", "Input should be a valid integer", v)


def _to_float(v: Any) -> float:
    if isinstance(v, bool):
        raise _bad("float_type", "Input should be a valid number, not a boolean", v)
    if isinstance(v, (int, float)):
        return float(v)
    if isinstance(v, str):
        try:
            return float(v.strip())
        except ValueError:
            raise _bad("float_parsing", "Input should be a valid number, unable to parse string as a number",
                       v) from None
    raise _bad("float_type", "Input should be a valid number", v)


def _to_bool(v: Any) -> bool:
    if isinstance(v, bool):
        return v
    if isinstance(v, int) and v in (0, 1):
        return bool(v)
    if isinstance(v, str) and v.strip().lower() in _TRUE | _FALSE:
        return v.strip().lower() in _TRUE
    raise _bad("bool_parsing", "Input should be a valid boolean (true or false)", v)


def _to_str(v: Any) -> str:
    if isinstance(v, str):
        return v
    raise _bad("string_type", "Input should be a valid string", v)


def _to_path(v: Any) -> Path:
    if isinstance(v, (str, Path)):
        return Path(v)
    raise _bad("path_type", "Input is not a valid path", v)


def _to_dict(v: Any) -> dict:
    if isinstance(v, dict):
        return dict(v)
    raise _bad("dict_type", "Input should be a valid dictionary", v)


def _literal(choices: tuple) -> Any:
    shown = [repr(c) for c in choices]
    words = shown[0] if len(shown) == 1 else f"{', '.join(shown[:-1])} or {shown[-1]}"

    def convert(v: Any) -> Any:
        for c in choices:
            if v == c and type(v) is type(c):
                return c
        raise _bad("literal_error", f"Input should be {words}", v)

    return convert


def _list(item: Any) -> Any:
    def convert(v: Any) -> list:
        if not isinstance(v, (list, tuple)):
            raise _bad("list_type", "Input should be a valid list", v)
        out, rows = [], []
        for i, x in enumerate(v):
            try:
                out.append(item(x))
            except _Bad as e:
                rows += [{**r, "loc": (i, *r["loc"])} for r in e.rows]
        if rows:
            raise _Bad(rows)
        return out

    return convert


def _optional(inner: Any) -> Any:
    return lambda v: None if v is None else inner(v)


def _model(cls: type[Model]) -> Any:
    def convert(v: Any) -> Model:
        if isinstance(v, cls):
            return v
        if not isinstance(v, dict):
            raise _bad("model_type", f"Input should be a valid dictionary or instance of {cls.__name__}", v)
        try:
            return cls(**v)
        except ValidationError as e:
            raise _Bad(e.errors()) from None

    return convert


def _instance(cls: type) -> Any:
    def convert(v: Any) -> Any:
        if isinstance(v, cls):
            return v
        raise _bad("is_instance_of", f"Input should be an instance of {cls.__name__}", v)

    return convert


_SCALARS = {int: _to_int, float: _to_float, bool: _to_bool, str: _to_str, Path: _to_path, dict: _to_dict}


def _converter(tp: Any) -> Any:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is Any:
        return lambda v: v
    if origin in (Union, types.UnionType):
        rest = [a for a in args if a is not type(None)]
        if len(rest) != 1 or len(args) != 2:
            raise TypeError(f"config_model: only `X | None` unions, not {tp}")
        return _optional(_converter(rest[0]))
    if origin is Literal:
        return _literal(args)
    if origin is list:
        return _list(_converter(args[0]) if args else (lambda v: v))
    if origin is dict:
        return _to_dict
    if tp in _SCALARS:
        return _SCALARS[tp]
    if isinstance(tp, type) and issubclass(tp, Model):
        return _model(tp)
    if isinstance(tp, type):
        return _instance(tp)
    raise TypeError(f"config_model: unsupported field type {tp}")


class Model:
    """Base of a settings model: fields from annotations, validated on construction (see the module doc)."""

    model_config: ClassVar[dict] = {}
    model_fields: ClassVar[dict[str, FieldInfo]] = {}
    _field_validators: ClassVar[dict[str, list]] = {}
    _model_validators: ClassVar[list] = []
    _resolved: ClassVar[bool] = False

    def __init_subclass__(cls, **kw: Any) -> None:
        super().__init_subclass__(**kw)
        fields = dict(getattr(cls, "model_fields", {}))
        field_validators: dict[str, list] = {k: list(v) for k, v in getattr(cls, "_field_validators", {}).items()}
        model_validators = list(getattr(cls, "_model_validators", []))
        for name in inspect.get_annotations(cls):
            if name.startswith("_") or name in ("model_config", "model_fields"):
                continue
            value = cls.__dict__.get(name, _REQUIRED)
            fields[name] = value if isinstance(value, FieldInfo) else FieldInfo(value)
            if name in cls.__dict__:
                delattr(cls, name)  # an instance always has it; a class never (pydantic's way)
        for attr, value in list(cls.__dict__.items()):
            if isinstance(value, _FieldValidator):
                for n in value.names:
                    field_validators.setdefault(n, []).append(value.func)
                setattr(cls, attr, value.func)
            elif isinstance(value, _ModelValidator):
                model_validators.append(value.func)
                setattr(cls, attr, value.func)
        cls.model_fields = fields
        cls._field_validators = field_validators
        cls._model_validators = model_validators
        cls._resolved = False

    @classmethod
    def _resolve(cls) -> None:
        """Converters from the annotations, on first use (a model may name one defined after it)."""
        hints = typing.get_type_hints(cls)
        for name, info in cls.model_fields.items():
            info.annotation = hints[name]
            info.convert = _converter(hints[name])
        cls._resolved = True

    def __init__(self, **data: Any) -> None:
        cls = type(self)
        if not cls.__dict__.get("_resolved"):
            cls._resolve()
        rows: list[dict] = []
        if cls.model_config.get("extra") == "forbid":
            rows += [{"type": "extra_forbidden", "loc": (k,), "msg": "Extra inputs are not permitted", "input": v}
                     for k, v in data.items() if k not in cls.model_fields]
        values: dict[str, Any] = {}
        for name, info in cls.model_fields.items():
            if name not in data:
                if info.is_required():
                    rows.append({"type": "missing", "loc": (name,), "msg": "Field required", "input": data})
                else:
                    values[name] = info.get_default(call_default_factory=True)
                continue
            v = data[name]
            try:
                v = info.convert(v)
                if v is not None:
                    info.check_bounds(v, data[name])
                for check in cls._field_validators.get(name, ()):
                    try:
                        v = check.__get__(None, cls)(v)
                    except ValueError as e:
                        raise _bad("value_error", str(e), data[name]) from None
            except _Bad as e:
                rows += [{**r, "loc": (name, *r["loc"])} for r in e.rows]
                continue
            values[name] = v
        if rows:
            raise ValidationError(cls.__name__, rows)
        self.__dict__.update(values)
        self.__dict__["_fields_set"] = {k for k in data if k in cls.model_fields}
        for check in cls._model_validators:
            try:
                check(self)
            except ValueError as e:
                if isinstance(e, ValidationError):
                    raise
                raise ValidationError(cls.__name__, [{"type": "value_error", "loc": (), "msg": str(e),
                                                      "input": data}]) from None

    # ---- pydantic's methods hammer uses ---------------------------------------------------------

    @classmethod
    def model_validate(cls, obj: Any) -> Any:
        if isinstance(obj, cls):
            return obj
        if not isinstance(obj, dict):
            raise ValidationError(cls.__name__, [{"type": "model_type", "loc": (), "input": obj,
                                                  "msg": f"Input should be a valid dictionary or instance of {cls.__name__}"}])
        return cls(**obj)

    @property
    def model_fields_set(self) -> set[str]:
        return set(self.__dict__["_fields_set"])

    def model_dump(self, *, exclude: Any = None, exclude_unset: bool = False, mode: str = "python") -> dict:
        out = {}
        for name in type(self).model_fields:
            if (exclude and name in exclude) or (exclude_unset and name not in self.__dict__["_fields_set"]):
                continue
            out[name] = _dump(self.__dict__[name], mode)
        return out

    def model_dump_json(self, *, indent: int | None = None, exclude: Any = None) -> str:
        return json.dumps(self.model_dump(exclude=exclude, mode="json"), indent=indent, ensure_ascii=False)

    def model_copy(self, *, update: dict | None = None, deep: bool = False) -> Any:
        import copy

        new = copy.deepcopy(self) if deep else copy.copy(self)
        new.__dict__["_fields_set"] = set(self.__dict__["_fields_set"]) | set(update or {})
        new.__dict__.update(update or {})
        return new

    def __copy__(self) -> Any:
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        return new

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return all(self.__dict__[k] == other.__dict__[k] for k in type(self).model_fields)

    __hash__ = None  # type: ignore[assignment] - mutable, like pydantic's models

    def __repr__(self) -> str:
        return f"{type(self).__name__}({', '.join(f'{k}={v!r}' for k in type(self).model_fields if (v := self.__dict__.get(k, _REQUIRED)) is not _REQUIRED)})"


def _dump(v: Any, mode: str) -> Any:
    if isinstance(v, Model):
        return v.model_dump(mode=mode)
    if isinstance(v, list):
        return [_dump(x, mode) for x in v]
    if isinstance(v, dict):
        return {k: _dump(x, mode) for k, x in v.items()}
    if mode == "json" and isinstance(v, Path):
        return str(v)
    return v
