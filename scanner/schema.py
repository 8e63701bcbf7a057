"""One validation layer for every file slscan reads: typed schemas on pydantic v2.

A file format is a `Schema` subclass next to the code that owns the file (the rig TOML in
`scanner.rig_schema`, the pattern set in `scanner.patterns`, the session manifest in
`scanner.session`, ...). `parse(SchemaClass, data, path)` turns whatever the file held into
the typed object or raises one `ConfigError` naming the file and the dotted key, in one line:

    rig.toml, key 'camera.bit_detph': unknown key in [camera]; did you mean 'bit_depth'?
    rig.toml, key 'rig.working_distance_mm': must be greater than 0, got -400.0

Every schema refuses unknown keys (with the nearest valid name), takes numbers strictly (no
strings, no booleans; an integer is accepted where a float is asked for) and refuses NaN and
infinity. Ranges are `Field` constraints; a rule across keys is a `model_validator` raising
ValueError with a message for people. Files whose content is a table of tables keyed by
names the user chooses (tolerances' faces) use `dict[str, SubSchema]`.
"""

from __future__ import annotations

import difflib
import types
import typing
import unicodedata
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, TypeVar

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, Strict, ValidationError

from scanner.config import load_toml
from scanner.errors import ConfigError

S = TypeVar("S", bound="Schema")

NOT_TEXT = frozenset({"Cc", "Cf", "Cs", "Zl", "Zp"})
"""Unicode categories refused in text: controls (NUL, TAB, line ends, ESC, DEL, C1), format
characters (zero-width, bidi overrides, soft hyphen, tags), lone surrogates (undecodable
bytes on the command line), line and paragraph separators."""
MAX_TEXT = 4096  # characters of one text value (a name, a serial, a path)


def plain_text(value: str, what: str = "text") -> str:
    """`value` unchanged if it is plain text: no character of a NOT_TEXT category, at most
    MAX_TEXT characters; else ValueError saying which character and where. The one
    boundary every user-given string passes (`Str` in every file schema; serials, operators
    and names on the command line and the station's screen), so nothing stored, shown or
    written to a terminal, HTML, CSV or a database carries them."""
    if not (value.isascii() and value.isprintable()):  # else plain ASCII: nothing to look at
        for i, c in enumerate(value):  # a name or a serial: a few dozen characters
            if unicodedata.category(c) in NOT_TEXT:
                raise ValueError(f"{what} holds the control character {c!r} at position {i}; only plain text is "
                                 f"accepted")
    if len(value) > MAX_TEXT:
        raise ValueError(f"{what} is {len(value)} characters long; at most {MAX_TEXT} are accepted")
    return value


Float = Annotated[float, Strict()]  # an int is accepted and becomes a float; NaN and inf are refused
Int = Annotated[int, Strict()]  # not a bool, not a float
Str = Annotated[str, Strict(), AfterValidator(plain_text)]
Bool = Annotated[bool, Strict()]
PositiveFloat = Annotated[float, Strict(), Field(gt=0)]
NonNegativeFloat = Annotated[float, Strict(), Field(ge=0)]
PositiveInt = Annotated[int, Strict(), Field(gt=0)]
Vector2 = Annotated[list[Float], Field(min_length=2, max_length=2)]
Vector3 = Annotated[list[Float], Field(min_length=3, max_length=3)]
Vector4 = Annotated[list[Float], Field(min_length=4, max_length=4)]
Matrix3 = Annotated[list[Vector3], Field(min_length=3, max_length=3)]
Matrix4 = Annotated[list[Vector4], Field(min_length=4, max_length=4)]


class Schema(BaseModel):
    """Base of every file schema: unknown keys refused, NaN and inf refused, immutable."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)


@dataclass(frozen=True)
class Source:
    """What `parse` tells the validators (their `ValidationInfo.context`): the file being
    read, for a record that validates more of itself later to name it."""

    path: str | Path


def parse(schema: type[S], data: Any, path: str | Path, prefix: str = "") -> S:
    """`data` validated as `schema`; `prefix` is the dotted name of `data` in the file (for
    a sub-table validated on its own). ConfigError naming the file and key otherwise."""
    try:
        return schema.model_validate(data, context=Source(path))
    except ValidationError as exc:
        raise _config_error(exc, schema, path, prefix) from None


def load(schema: type[S], path: str | Path) -> S:
    """A TOML file validated as `schema`."""
    return parse(schema, load_toml(path), path)


def dotted(loc: tuple[Any, ...], prefix: str = "") -> str:
    """('objects', 2, 'pose') -> 'objects[2].pose' (after `prefix`)."""
    out = prefix
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def nearest(name: str, choices: typing.Iterable[str]) -> str | None:
    """The valid name closest to a misspelt one, or None when nothing is close."""
    found = difflib.get_close_matches(name, sorted(choices), n=1, cutoff=0.6)
    return found[0] if found else None


def unknown_key_problem(key: str, allowed: typing.Iterable[str], table: str) -> str:
    """The message for an unknown key: the nearest valid name, else the valid names."""
    allowed = sorted(allowed)
    where = f"[{table}]" if table else "the top level"
    guess = nearest(key, allowed)
    return (f"unknown key in {where}; did you mean '{guess}'?" if guess
            else f"unknown key in {where}; valid keys: {', '.join(allowed)}")


def _config_error(exc: ValidationError, schema: type[BaseModel], path: str | Path, prefix: str) -> ConfigError:
    errors = exc.errors(include_url=False)
    # an unknown key first (a misspelt table also makes its keys "missing"), then the most
    # specific error: a deeper key says more than a summary of the table around it
    e = max(errors, key=lambda err: (err["type"] == "extra_forbidden", len(err["loc"])))
    loc = tuple(e["loc"])
    key = dotted(loc, prefix) or None
    kind, value = e["type"], e.get("input")
    if kind == "extra_forbidden":
        parent = _schema_at(schema, loc[:-1])
        allowed = parent.model_fields if isinstance(parent, type) and issubclass(parent, BaseModel) else {}
        problem = unknown_key_problem(str(loc[-1]), allowed, dotted(loc[:-1], prefix))
    elif kind == "missing":
        problem = "required key is missing"
    elif kind in ("too_short", "too_long"):
        n = (e.get("ctx") or {}).get("min_length" if kind == "too_short" else "max_length")
        problem = f"expected a list of {n} values, got {_show(value)}"
    elif kind in ("model_type", "dict_type", "model_attributes_type"):
        problem = f"expected a table, got {_show(value)}"
    elif kind == "list_type":
        problem = f"expected a list, got {_show(value)}"
    elif kind == "finite_number":
        problem = f"must be a finite number, got {_show(value)}"
    elif kind in ("float_type", "int_type", "string_type", "bool_type", "int_from_float"):
        what = {"float_type": "a number", "int_type": "a whole number", "int_from_float": "a whole number",
                "string_type": "a string", "bool_type": "true or false"}[kind]
        problem = f"expected {what}, got {_show(value)}"
    elif kind == "value_error":
        problem = str(e["msg"]).removeprefix("Value error, ")
    elif kind in ("greater_than", "greater_than_equal", "less_than", "less_than_equal") and _range(schema, loc):
        problem = f"must lie within {_range(schema, loc)}, got {_show(value)}"
    else:
        problem = f"{str(e['msg']).replace('Input should be', 'must be')}, got {_show(value)}"
    return ConfigError(path, key, problem)


def _range(schema: Any, loc: tuple[Any, ...]) -> str | None:
    """The documented range of the field at `loc` ("[0, 10]", "(0, 3600]"), when it has both bounds."""
    parent = _schema_at(schema, loc[:-1])
    if not (isinstance(parent, type) and issubclass(parent, BaseModel)) or not isinstance(loc[-1], str):
        return None
    field = parent.model_fields.get(loc[-1])
    if field is None:
        return None
    bounds: dict[str, Any] = {}
    stack = [field.annotation, *field.metadata]
    while stack:  # the constraints sit in Field(...) metadata, possibly inside Annotated inside X | None
        t = stack.pop()
        for name in ("ge", "gt", "le", "lt"):
            if getattr(t, name, None) is not None:
                bounds[name] = getattr(t, name)
        stack += list(getattr(t, "metadata", ()) or ()) + list(typing.get_args(t))
    lo = ("[", bounds["ge"]) if "ge" in bounds else ("(", bounds["gt"]) if "gt" in bounds else None
    hi = ("]", bounds["le"]) if "le" in bounds else (")", bounds["lt"]) if "lt" in bounds else None
    if lo is None or hi is None:
        return None
    return f"{lo[0]}{lo[1]:g}, {hi[1]:g}{hi[0]}"


def _show(value: Any) -> str:
    text = repr(value) if not isinstance(value, (dict, list)) else f"{type(value).__name__} {value!r}"
    return text if len(text) <= 80 else text[:77] + "..."


def _schema_at(schema: Any, loc: tuple[Any, ...]) -> Any:
    """The type found by following `loc` (field names, list indices, dict keys) from `schema`."""
    t = schema
    for part in loc:
        t = _unwrap(t)
        if isinstance(t, type) and issubclass(t, BaseModel):
            field = t.model_fields.get(part) if isinstance(part, str) else None
            if field is None:
                return None
            t = field.annotation
            continue
        origin, args = typing.get_origin(t), typing.get_args(t)
        if origin in (list, tuple) and args:
            t = args[0]
        elif origin is dict and len(args) == 2:
            t = args[1]
        else:
            return None
    return _unwrap(t)


def _unwrap(t: Any) -> Any:
    """Strip Annotated and Optional (`X | None`) down to the type inside."""
    while True:
        origin = typing.get_origin(t)
        if origin is Annotated:
            t = typing.get_args(t)[0]
        elif origin in (typing.Union, types.UnionType):
            inner = [a for a in typing.get_args(t) if a is not type(None)]
            if len(inner) != 1:
                return t
            t = inner[0]
        else:
            return t
