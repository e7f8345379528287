"""The one strict TOML → frozen-dataclass loader of uavloc's files: mission files, scenario files,
campaign specs (and the estimator options inside them).

The TOML keys ARE the field names of the dataclass (`[flight] budget_m = 1200`). Everything a file
may get wrong is refused here, once, with the file, the key path and the value in the message:

- an unknown key (with the right name when only its unit is wrong: `budget_km` → `budget_m`);
- a value of the wrong type (a TOML string where a number belongs, an integer written as a float);
- a NaN or an infinity;
- a number outside its field's range (:func:`bounded`: what a multicopter mission can mean);
- an integer written as a string: only hex with `0x` (`"0x4601"`, the way RNTIs are written;
  OAI prints RNTIs in hex without a prefix, so a bare digit string such as `"4601"` is ambiguous
  and refused);
- a file that is not UTF-8 or not TOML (:func:`read_toml`).

Each kind of file raises its own :class:`uavloc.errors.UavlocError` subclass (`error=`).
Checks across fields (alt_min_m ≤ altitude_m, distinct RNTIs, ...) belong to each file's validator.
"""

from __future__ import annotations

import dataclasses
import math
import re
import tomllib
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from uavloc.errors import MissionConfigError, UavlocError

ErrorType = type[UavlocError]

#: a name that also names files or folders (a campaign's, a family's): one word of letters, digits,
#: '_', '-' and '.', not '.' or '..', so it never names a folder elsewhere
SAFE_NAME = re.compile(r"(?!\.{1,2}$)[A-Za-z0-9_.\-]+")

#: unit suffixes of key names (a key whose name differs from a field's only here has the wrong unit)
UNIT_SUFFIX = re.compile(r"_(m|km|ft|s|ms|min|h|mps|kmh|kph|pct|deg|rad|hz|khz|mhz|per_m|m2|mps2|db|db_at_100m)$")


@dataclass(frozen=True)
class Bounds:
    """The allowed values of a number: lo ≤ x ≤ hi, with `lo_open`: lo < x."""

    lo: float
    hi: float
    lo_open: bool = False
    what: str = ""

    def holds(self, x: float) -> bool:
        return (x > self.lo if self.lo_open else x >= self.lo) and x <= self.hi

    def __str__(self) -> str:
        if self.what:
            return self.what
        if self.lo == 0:
            return f"must be {'positive' if self.lo_open else '>= 0'} and at most {self.hi:g}"
        return f"must be in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}]"


def bounded(default: Any, lo: float, hi: float, *, lo_open: bool = False, what: str = "") -> Any:
    """A dataclass field (default: `default`; dataclasses.MISSING: required) whose numbers must lie
    in [lo, hi] ((lo, hi] with `lo_open`); None (for an optional field) is always allowed.
    what: the message when not (default: the range). Checked by :func:`build`."""
    return dataclasses.field(default=default, metadata={"bounds": Bounds(float(lo), float(hi), lo_open, what)})


def like(cls: type, name: str, default: Any = dataclasses.MISSING) -> Any:
    """A new dataclass field with the default (or `default`) and the bounds of the field `name` of
    the dataclass `cls`: one definition of a number that two schemas share (a simulated world's
    truth and what the mission assumes of it)."""
    f = cls.__dataclass_fields__[name]
    if default is dataclasses.MISSING:
        default = f.default
    return dataclasses.field(default=default, metadata=f.metadata)


def positive(default: Any, hi: float) -> Any:
    """A dataclass field whose numbers must lie in (0, hi]."""
    return bounded(default, 0.0, hi, lo_open=True)


def fail(where: str, key: str, value: Any, problem: str, error: ErrorType = MissionConfigError) -> UavlocError:
    """The error of one bad value: `<where>: key 'a.b' = <value>: <problem>`."""
    return error(f"{where}: key {key!r} = {value!r}: {problem}")


def check_bounds(obj: Any, where: str, prefix: str = "", error: ErrorType = MissionConfigError) -> None:
    """Raise unless every bounded field of the dataclass `obj` (and of the dataclasses it holds)
    is within its :class:`Bounds`."""
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        key = f"{prefix}.{f.name}" if prefix else f.name
        b = f.metadata.get("bounds")
        if b is not None:
            for v in value if isinstance(value, list | tuple) else (value,):
                if v is not None and not b.holds(v):
                    raise fail(where, key, value, str(b), error)
        if dataclasses.is_dataclass(value):
            check_bounds(value, where, key, error)
        elif isinstance(value, list | tuple):
            for i, item in enumerate(value):
                if dataclasses.is_dataclass(item):
                    check_bounds(item, where, f"{key}[{i}]", error)


def _convert(value: Any, tp: Any, where: str, key: str, error: ErrorType, explain: Explain | None) -> Any:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        first: UavlocError | None = None
        for a in inner:
            try:
                return _convert(value, a, where, key, error, explain)
            except UavlocError as exc:
                first = first or exc
        assert first is not None
        raise first
    if origin is Literal:
        if value not in args:
            raise fail(where, key, value, f"must be one of {', '.join(map(repr, args))}", error)
        return value
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise fail(where, key, value, "expected a table", error)
        return build(tp, value, where, key, error=error, explain=explain, check=False)
    if origin in (tuple, list):
        if not isinstance(value, list):
            raise fail(where, key, value, "expected a list", error)
        if origin is list or (len(args) == 2 and args[1] is Ellipsis):
            out = [_convert(v, args[0], where, f"{key}[{i}]", error, explain) for i, v in enumerate(value)]
            return out if origin is list else tuple(out)
        if len(value) != len(args):
            what = "numbers" if all(a is float for a in args) else "values"
            raise fail(where, key, value, f"expected {len(args)} {what}", error)
        return tuple(_convert(v, a, where, f"{key}[{i}]", error, explain)
                     for i, (v, a) in enumerate(zip(value, args, strict=True)))
    if origin is dict:
        if not isinstance(value, dict):
            raise fail(where, key, value, "expected a table", error)
        if args and dataclasses.is_dataclass(args[1]):  # a table of tables by name: [truth.ue1]
            return {k: _convert(v, args[1], where, f"{key}.{k}", error, explain) for k, v in value.items()}
        return dict(value)
    if tp is bool:
        if not isinstance(value, bool):
            raise fail(where, key, value, "expected true or false", error)
        return value
    if tp is int:
        if isinstance(value, str):  # RNTIs are often written in hex: "0x4601"
            if not value.strip().lower().startswith("0x"):
                raise fail(where, key, value, "expected an integer; a string must be hex with 0x "
                           f"(\"0x{value.strip()}\"), or write the decimal number unquoted", error)
            try:
                return int(value, 16)
            except ValueError:
                raise fail(where, key, value, "expected an integer (hex with 0x)", error) from None
        if isinstance(value, bool) or not isinstance(value, int):
            raise fail(where, key, value, "expected an integer", error)
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            hint = " (the unit is in the key's name; write the number alone)" if isinstance(value, str) else ""
            raise fail(where, key, value, f"expected a number{hint}", error)
        if not math.isfinite(value):
            raise fail(where, key, value, "must be a finite number", error)
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise fail(where, key, value, "expected a string", error)
        return value
    raise fail(where, key, value, f"unsupported type {tp!r}", error)  # pragma: no cover - schema bug


#: explain(cls, name) → why the unknown key `name` of a `cls` table is wrong, or None
Explain = Callable[[type, str], str | None]


def _unknown_key(cls: type, name: str, value: Any, where: str, key: str, error: ErrorType,
                 explain: Explain | None) -> UavlocError:
    fields = {f.name for f in dataclasses.fields(cls)}
    why = explain(cls, name) if explain is not None else None
    if why:
        return fail(where, key, value, why, error)
    stem = UNIT_SUFFIX.sub("", name)
    same = sorted(f for f in fields if UNIT_SUFFIX.sub("", f) == stem and f != name)
    if same:
        return fail(where, key, value, f"wrong unit: the key is {' or '.join(map(repr, same))} "
                    "(units are part of the key names)", error)
    return fail(where, key, value, f"unknown key {name!r}; allowed here: {', '.join(sorted(fields))}", error)


def build(cls: type, data: Any, where: str, prefix: str = "", *, error: ErrorType = MissionConfigError,
          explain: Explain | None = None, check: bool = True) -> Any:
    """An instance of the dataclass `cls` from a parsed TOML table, strictly (see the module
    docstring). where: the file (for messages); prefix: the table's key path; error: the error
    type; explain: a reason for an unknown key (e.g. a true position in a mission file); check:
    also check every field's bounds (the nested tables' too)."""
    if not isinstance(data, dict):
        raise fail(where, prefix or "(document)", data, "expected a table", error)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for name, value in data.items():
        key = f"{prefix}.{name}" if prefix else name
        if name not in fields:
            raise _unknown_key(cls, name, value, where, key, error, explain)
        kwargs[name] = _convert(value, hints[name], where, key, error, explain)
    for name, f in fields.items():
        if name not in kwargs and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise error(f"{where}: missing required key {name!r}" + (f" in {prefix!r}" if prefix else ""))
    obj = cls(**kwargs)
    if check:
        check_bounds(obj, where, prefix, error)
    return obj


def read_toml(path: str | Path, what: str, error: ErrorType = MissionConfigError) -> dict:
    """The parsed TOML document of the file `path` (what: "mission file", "scenario", ...), or an
    `error` naming the file when it cannot be read, is not UTF-8 or is not TOML."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise error(f"{p}: cannot read the {what}: {exc.strerror or exc}") from exc
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{p}: the {what} is not UTF-8 text (byte {exc.start}: {raw[exc.start:exc.start + 1]!r})") \
            from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{p}: not valid TOML: {exc}") from exc
