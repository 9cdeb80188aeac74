"""Settings declared once (type, default, unit, range, doc) and validated by one function.

A config dataclass declares each of its settings with :func:`setting`; the
annotation gives the type, the declaration everything else::

    @dataclass(frozen=True)
    class RecorderSettings:
        flush_interval_s: float = setting(1.0, "crash-loss bound", unit="s", gt=0)
        compression: str = setting("zstd", "chunk compression", choices=("zstd", "lz4", "none"))

:func:`build` makes one from a table (a parsed TOML table, CLI overrides),
checking unknown keys, types, finiteness, ranges and choices, and naming the
place (file, table, key) and what was expected in a ``ConfigError``. Nothing
else checks settings: a class keeps in ``__post_init__`` only what involves
several of its fields. :func:`describe` and :func:`to_table` give the
declarations and values back for ``mntes-stream config show``, CLI help and
file metadata.

Supported annotations: ``bool``, ``int``, ``float``, ``str``, ``complex``
(a number or ``[re, im]``), ``tuple[T, ...]``, ``tuple[T, T]``, ``T | None``
and nested setting dataclasses (a sub-table). ``from __future__ import
annotations`` is fine: annotations are resolved with ``typing.get_type_hints``.

Examples
--------
>>> from dataclasses import dataclass
>>> @dataclass(frozen=True)
... class Demo:
...     rate_hz: float = setting(1.0, "how often", unit="Hz", gt=0)
>>> build(Demo, {"rate_hz": 5}).rate_hz
5.0
>>> build(Demo, {"rate_hz": "5"}, "demo.toml [demo]")
Traceback (most recent call last):
...
mntes_stream.errors.ConfigError: demo.toml [demo] rate_hz: expected a number (Hz) > 0, got '5'
"""

from __future__ import annotations

import dataclasses
import functools
import math
import operator
import os.path
import re
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from mntes_stream.errors import ConfigError

__all__ = ["Settings", "validate", "Setting", "setting", "build", "build_document", "document_tables", "check_value", "describe", "to_table",
           "declared", "is_settings"]

_KEY = "mntes.setting"


@dataclass(frozen=True)
class Setting:
    """What one setting declares besides its type and default.

    Attributes
    ----------
    doc : str
        One line for humans (CLI help, ``config show``).
    unit : str
        Physical unit, e.g. ``"s"``, ``"K"``, ``"W"`` ("" for none).
    ge, gt, le, lt : float or None
        Bounds; for tuples they apply to every element.
    choices : tuple or None
        The only values allowed.
    allow_inf : bool
        +inf is allowed (e.g. "never stale"); NaN never is.
    increasing : bool
        A tuple whose elements must increase strictly (``[low, high]``).
    path : bool
        A file or directory name (or a list of them): :func:`build` given a
        ``base_dir`` resolves a relative one against it, the directory of the
        file that names it.
    pattern : re.Pattern or None
        A string must match it whole (e.g. ``core.ids.NAME_PATTERN``).
    flatten : bool
        A settings dataclass whose keys sit in the parent's own table
        instead of a sub-table of its own.
    """

    doc: str = ""
    unit: str = ""
    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    choices: tuple | None = None
    allow_inf: bool = False
    increasing: bool = False
    path: bool = False
    pattern: re.Pattern | None = None
    flatten: bool = False

    def bounds_text(self) -> str:
        parts = [f"{op} {v:g}" for op, v in ((">=", self.ge), (">", self.gt), ("<=", self.le), ("<", self.lt)) if v is not None]
        return " and ".join(parts)


def setting(default: Any = dataclasses.MISSING, doc: str = "", *, default_factory: Any = dataclasses.MISSING,
            **declared_: Any) -> Any:
    """A dataclass field carrying its :class:`Setting` (keywords as its attributes)."""
    meta = {_KEY: Setting(doc=doc, **declared_)}
    if default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    if isinstance(default, list):
        default = tuple(default)
    return dataclasses.field(default=default, metadata=meta)


def declared(field: dataclasses.Field) -> Setting:
    """The :class:`Setting` of a field (an empty one for fields declared without :func:`setting`)."""
    return field.metadata.get(_KEY) or Setting()


def is_settings(cls: Any) -> bool:
    """Whether ``cls`` is a settings dataclass (a table)."""
    return isinstance(cls, type) and dataclasses.is_dataclass(cls)


_HINTS: dict[type, dict[str, Any]] = {}


def _hints(cls: type) -> dict[str, Any]:
    hints = _HINTS.get(cls)
    if hints is None:
        hints = _HINTS[cls] = typing.get_type_hints(cls)
    return hints


def _args(hint: Any) -> tuple[Any, tuple]:
    return typing.get_origin(hint), typing.get_args(hint)


def _optional_inner(hint: Any) -> Any | None:
    """``T`` for ``T | None``, else None."""
    origin, args = _args(hint)
    if origin in (typing.Union, types.UnionType) and type(None) in args:
        rest = [a for a in args if a is not type(None)]
        return rest[0] if len(rest) == 1 else functools.reduce(operator.or_, rest)
    return None


def expected(hint: Any, s: Setting = Setting(), plural: bool = False) -> str:
    """Words for what a setting takes, e.g. ``a number (s) >= 0``."""
    inner = _optional_inner(hint)
    if inner is not None:
        return f"{expected(inner, s, plural)} or absent"
    origin, args = _args(hint)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {expected(args[0], s, True)}"
        what = f"a list of {len(args)} {expected(args[0], s, True)}" if len(set(args)) == 1 else \
            f"a list [{', '.join(expected(a) for a in args)}]"
        return what + (" increasing" if s.increasing else "")
    if s.choices is not None:
        return "one of " + ", ".join(repr(c) for c in s.choices)
    if s.pattern is not None and hint is str:
        return f"a name matching {s.pattern.pattern.strip(chr(92) + 'AZ')}"
    one = {bool: "true or false", int: "an integer", float: "a number", str: "a string",
           complex: "a number or [re, im]"}
    many = {bool: "booleans", int: "integers", float: "numbers", str: "strings", complex: "numbers or [re, im] pairs"}
    words = (many if plural else one).get(hint) or getattr(hint, "__name__", str(hint))
    if s.unit and hint in (int, float, complex):
        words += f" ({s.unit})"
    if hint in (int, float) and s.bounds_text():
        words += " " + s.bounds_text()
    return words


class _Bad(Exception):
    """A value that does not fit; the caller adds the place."""


def _number(value: Any, s: Setting, integer: bool) -> int | float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _Bad
    if integer:
        if not isinstance(value, int):
            raise _Bad
        out: int | float = value
    else:
        out = float(value)
        if math.isnan(out) or (math.isinf(out) and not (s.allow_inf and out > 0)):
            raise _Bad
    for bound, ok in ((s.ge, lambda b: out >= b), (s.gt, lambda b: out > b), (s.le, lambda b: out <= b),
                      (s.lt, lambda b: out < b)):
        if bound is not None and not ok(bound):
            raise _Bad
    return out


def _convert(value: Any, hint: Any, s: Setting) -> Any:
    """``value`` as ``hint`` or raise _Bad; tuples come from lists."""
    inner = _optional_inner(hint)
    if inner is not None:
        return None if value is None else _convert(value, inner, s)
    origin, args = _args(hint)
    if origin is tuple:
        if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)):
            raise _Bad
        if len(args) == 2 and args[1] is Ellipsis:
            out = tuple(_convert(v, args[0], s) for v in value)
        else:
            if len(value) != len(args):
                raise _Bad
            out = tuple(_convert(v, a, s) for v, a in zip(value, args))
        if s.increasing and any(not a < b for a, b in zip(out, out[1:])):
            raise _Bad
        return out
    if hint is bool:
        if not isinstance(value, bool):
            raise _Bad
        out = value
    elif hint is int or hint is float:
        out = _number(value, s, hint is int)
    elif hint is str:
        if not isinstance(value, str) or (s.pattern is not None and not s.pattern.fullmatch(value)):
            raise _Bad
        out = value
    elif hint is complex:
        if isinstance(value, (list, tuple)) and len(value) == 2:
            re_, im_ = (_number(v, Setting(), False) for v in value)
            out = complex(re_, im_)
        elif isinstance(value, complex):
            if not (math.isfinite(value.real) and math.isfinite(value.imag)):
                raise _Bad
            out = value
        else:
            out = complex(_number(value, Setting(), False))
    elif hint is tuple:  # a bare ``tuple``: any list, its items left to the class
        if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)):
            raise _Bad
        return tuple(value)
    elif is_settings(hint):
        if isinstance(value, hint):
            return value
        raise _Bad
    elif isinstance(hint, type):
        if not isinstance(value, hint):
            raise _Bad
        out = value
    else:  # an annotation this module does not know: the class decides
        return value
    if s.choices is not None and out not in s.choices:
        raise _Bad
    return out


def check_value(cls: type, name: str, value: Any, where: str = "") -> Any:
    """One setting of ``cls`` checked and converted, or a ConfigError naming ``where`` and ``name``.

    >>> import dataclasses
    >>> @dataclasses.dataclass(frozen=True)
    ... class D:
    ...     pair: tuple[float, float] = setting((0.0, 1.0), "range", increasing=True)
    >>> check_value(D, "pair", [2, 3])
    (2.0, 3.0)
    """
    field = {f.name: f for f in dataclasses.fields(cls)}.get(name)
    if field is None:
        raise ConfigError(f"{_place(where, name)}: unknown setting")
    s, hint = declared(field), _hints(cls)[name]
    try:
        return _convert(value, hint, s)
    except (_Bad, TypeError, ValueError, OverflowError):
        raise ConfigError(f"{_place(where, name)}: expected {expected(hint, s)}, got {value!r}") from None


def validate(obj: Any, where: str = "") -> None:
    """Check (and convert in place: lists to tuples, ints to floats) every field of a frozen settings object."""
    cls = type(obj)
    for f in dataclasses.fields(obj):
        if f.init:
            value = getattr(obj, f.name)
            checked = check_value(cls, f.name, value, where)
            if checked is not value:
                object.__setattr__(obj, f.name, checked)


class Settings:
    """Base of settings dataclasses: every field is checked against its declaration on construction.

    A subclass with a ``__post_init__`` of its own (checks across fields)
    calls ``super().__post_init__()`` first.
    """

    def __post_init__(self) -> None:
        validate(self)


def _sub(where: str, name: str) -> str:
    """The place of a sub-table: ``file [a]`` then ``file [a.b]``."""
    if where.endswith("]"):
        return f"{where[:-1]}.{name}]"
    return f"{where} [{name}]" if where else f"[{name}]"


def _place(where: str, name: str) -> str:
    return f"{where} {name}" if where else name


def _resolve(value: Any, base_dir: str) -> Any:
    if isinstance(value, str):
        # "~/x" names a home directory, not a path relative to the config file.
        return os.path.join(base_dir, value) if value and not os.path.isabs(os.path.expanduser(value)) else value
    if isinstance(value, (list, tuple)):
        return type(value)(_resolve(v, base_dir) for v in value)
    return value


def build(cls: type, table: Mapping[str, Any] | None = None, where: str = "", base_dir: str | None = None,
          **fixed: Any) -> Any:
    """``cls`` from a table of settings, every value checked against its declaration.

    Parameters
    ----------
    cls : settings dataclass
    table : mapping
        Keys are field names; a nested settings dataclass takes a mapping (a
        sub-table), a ``flatten`` one takes its keys from this table.
    where : str
        The place for error messages, e.g. ``"services/recorder.toml [recorder]"``.
    base_dir : str, optional
        Relative ``path`` settings in ``table`` are resolved against it.
    **fixed
        Values that do not come from a file (already typed objects); checked too.

    Raises
    ------
    ConfigError
        Unknown key, wrong type, out of range, or what ``__post_init__`` rejects.
    """
    if table is None:
        table = {}
    if not isinstance(table, Mapping):
        raise ConfigError(f"{where or cls.__name__}: expected a table, got {table!r}")
    hints = _hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    flat = {n: {g.name for g in dataclasses.fields(hints[n]) if g.init} for n, f in fields.items() if declared(f).flatten}
    own = set(fields) - set(flat)
    unknown = sorted(set(table) - own - set().union(*flat.values()))
    if unknown:
        known = sorted(own.union(*flat.values()))
        raise ConfigError(f"{where or cls.__name__}: unknown key(s) {unknown} (known: {known})")
    kwargs: dict[str, Any] = {}
    for name, keys_ in flat.items():
        if name not in fixed:
            kwargs[name] = build(hints[name], {k: v for k, v in table.items() if k in keys_}, where, base_dir)
    for name, value in [(k, v) for k, v in table.items() if k in own] + list(fixed.items()):
        hint = hints[name]
        if is_settings(hint) and isinstance(value, Mapping):
            kwargs[name] = build(hint, value, _sub(where, name), base_dir)
            continue
        value = kwargs[name] = check_value(cls, name, value, where)
        if base_dir is not None and name not in fixed and declared(fields[name]).path:
            kwargs[name] = _resolve(value, base_dir)
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}" if where else str(exc)) from None
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where or cls.__name__}: {exc}") from None


def document_tables(cls: type, main: str) -> dict[str, str]:
    """The tables of a whole config document for ``cls``: ``{table: field}`` (``main`` maps to "")."""
    hints = _hints(cls)
    out = {main: ""}
    for f in dataclasses.fields(cls):
        if f.init and is_settings(hints[f.name]) and not declared(f).flatten:
            out[f.name] = f.name
    return out


def build_document(cls: type, doc: Mapping[str, Any], main: str, where: str = "", base_dir: str | None = None,
                   **fixed: Any) -> Any:
    """A whole config document: ``cls``'s own settings from ``[main]``, each sub-table field from its own table.

    >>> import dataclasses
    >>> @dataclasses.dataclass(frozen=True)
    ... class Svc:
    ...     port: int = setting(7447, "port", ge=1, le=65535)
    >>> build_document(Svc, {"svc": {"port": 1}}, "svc")
    Svc(port=1)
    >>> build_document(Svc, {"svc": {"port": 0}}, "svc", "x.toml")
    Traceback (most recent call last):
    ...
    mntes_stream.errors.ConfigError: x.toml [svc] port: expected an integer >= 1 and <= 65535, got 0
    >>> build_document(Svc, {"svc": {}, "net": {}}, "svc", "x.toml")
    Traceback (most recent call last):
    ...
    mntes_stream.errors.ConfigError: x.toml: unknown table(s) ['net'] (expected [svc])
    """
    if not isinstance(doc, Mapping):
        raise ConfigError(f"{where or main}: expected a document of tables")
    tables = document_tables(cls, main)
    unknown = sorted(set(doc) - set(tables))
    if unknown:
        expected_ = ", ".join(f"[{t}]" for t in tables)
        raise ConfigError(f"{where or main}: unknown table(s) {unknown} (expected {expected_})")
    for t in tables:
        if not isinstance(doc.get(t, {}), Mapping):
            raise ConfigError(f"{where or main}: {t} must be a table [{t}], got {doc[t]!r}")
    misplaced = sorted(set(doc.get(main, {})) & (set(tables) - {main}))
    if misplaced:
        raise ConfigError(f"{_sub(where, main)}: {misplaced[0]} goes in a table of its own, [{misplaced[0]}]")
    subs = {f: build(_hints(cls)[f], doc.get(t, {}), _sub(where, t), base_dir)
            for t, f in tables.items() if f and f not in fixed}
    return build(cls, doc.get(main, {}), _sub(where, main), base_dir, **subs, **fixed)


def to_table(obj: Any) -> dict[str, Any]:
    """The values of a settings object as TOML-ready data (tuples as lists, complex as [re, im], None left out)."""

    def plain(v: Any) -> Any:
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            return to_table(v)
        if isinstance(v, (tuple, list)):
            return [plain(x) for x in v]
        if isinstance(v, complex):
            return [v.real, v.imag]
        return v

    return {f.name: plain(getattr(obj, f.name)) for f in dataclasses.fields(obj) if getattr(obj, f.name) is not None}


def describe(cls: type) -> list[dict[str, Any]]:
    """One entry per setting: name, expected (words), default, unit, doc; sub-tables as ``table``."""
    out = []
    hints = _hints(cls)
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        s, hint = declared(f), hints[f.name]
        entry: dict[str, Any] = {"name": f.name, "expected": expected(hint, s), "unit": s.unit, "doc": s.doc}
        if f.default is not dataclasses.MISSING:
            entry["default"] = f.default
        elif f.default_factory is not dataclasses.MISSING:
            entry["default"] = f.default_factory()
        if is_settings(hint):
            entry["table"] = describe(hint)
        out.append(entry)
    return out
