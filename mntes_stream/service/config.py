"""Config documents from files: which service, its settings with every layer applied, paths resolved.

A service config file is TOML with the service's main table (``[converter]``,
``[recorder]``, ...; see ``service.registry``) and its sub-tables
(``[zenoh]``, ...). Relative file names in it resolve against the file's own
directory. ``--set TABLE.KEY=VALUE`` overrides a value (relative names there
resolve against the current directory), the zenoh flags override ``[zenoh]``.
"""

from __future__ import annotations

import dataclasses
import os
import tomllib
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from mntes_stream.core.settings import check_value, declared, document_tables, to_table
from mntes_stream.errors import ConfigError

__all__ = ["read_toml", "service_of", "apply_overrides", "load_service_config", "config_of", "with_zenoh", "file_kind",
           "check_file", "check_paths", "show_file"]

# What `config check` takes for a config file; anything else it is given is skipped, said in a note.
CONFIG_SUFFIXES = (".toml", ".json5", ".json")


def read_toml(path: str | Path) -> dict:
    """A TOML file as a dict; one-line ConfigError for a missing, unreadable or malformed file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read: {getattr(exc, 'strerror', None) or exc}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None


def service_of(doc: dict, where: str):
    """The registry service whose main table the document has (exactly one)."""
    from mntes_stream.service.registry import SERVICES

    found = [name for name in SERVICES if name in doc]
    if len(found) != 1:
        tables = ", ".join(f"[{n}]" for n in SERVICES)
        got = ", ".join(f"[{n}]" for n in found) or f"tables {sorted(doc)}"
        raise ConfigError(f"{where}: a service config has exactly one of {tables}; found {got}")
    return SERVICES[found[0]]


def _parse_value(text: str) -> Any:
    """A TOML value (``5``, ``1.5``, ``true``, ``"x"``, ``[1, 2]``), else the text itself."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def apply_overrides(doc: dict, items: Iterable[str], service=None) -> dict:
    """``doc`` with ``TABLE.KEY=VALUE`` items applied (a copy); path settings made absolute (current directory)."""
    doc = {k: dict(v) if isinstance(v, dict) else v for k, v in doc.items()}
    for item in items:
        name, sep, text = item.partition("=")
        table, dot, key = name.strip().rpartition(".")
        if not sep or not dot or not table or not key:
            raise ConfigError(f"--set {item!r}: expected TABLE.KEY=VALUE, e.g. recorder.directory=/data")
        value = _parse_value(text.strip())
        if service is not None:
            # Checked here, so a bad value is blamed on the command line, not on the file it would go into.
            holder = _holder(service.Config, service.name, table, key, item)
            if not isinstance(value, dict):  # an inline table is a sub-table: build() checks its keys
                check_value(holder, key, value, f"command line --set [{table}]")
            if declared({f.name: f for f in dataclasses.fields(holder)}[key]).path:
                value = [os.path.abspath(v) for v in value] if isinstance(value, list) else os.path.abspath(str(value))
        target = doc.setdefault(table, {})
        if not isinstance(target, dict):
            raise ConfigError(f"--set {item!r}: {table} is not a table")
        target[key] = value
    return doc


def _holder(cls, main: str, table: str, key: str, item: str) -> type:
    """The settings class that declares ``table.key`` in a ``[main]`` document (a ConfigError naming the
    command line's ``item`` when none does)."""
    import typing

    tables = document_tables(cls, main)
    if table not in tables:
        raise ConfigError(f"command line --set {item!r}: a [{main}] config has no table [{table}] "
                          f"(tables: {', '.join(tables)})")
    sub = cls if table == main else typing.get_type_hints(cls)[tables[table]]
    for f in dataclasses.fields(sub):
        if f.name == key and f.init:
            return sub
        if declared(f).flatten:
            inner = typing.get_type_hints(sub)[f.name]
            if any(g.name == key and g.init for g in dataclasses.fields(inner)):
                return inner
    known = sorted(f.name for f in dataclasses.fields(sub) if f.init)
    raise ConfigError(f"command line --set {item!r}: [{table}] has no setting {key!r} (known: {known})")


def load_service_config(path: str | Path, overrides: Iterable[str] = ()):
    """``(service class, config)`` from a service config file, ``--set`` items applied."""
    doc = read_toml(path)
    service = service_of(doc, str(path))
    doc = apply_overrides(doc, overrides, service)
    base = str(Path(path).resolve().parent)
    return service, service.config_from_document(doc, str(path), base_dir=base)


def config_of(service_cls, path, overrides: Iterable[str] = ()):
    """``service_cls``'s config: its file (``--config``, with ``--set`` items) or, without one, its defaults.

    Raises ConfigError for a file of another service, or ``--set`` items without a file.
    """
    if path:
        service, cfg = load_service_config(path, overrides)
        if service is not service_cls:
            raise ConfigError(f"{path}: a [{service.name}] config, not a [{service_cls.name}] one")
        return cfg
    if overrides:
        raise ConfigError("--set needs --config")
    return service_cls.Config()


def with_zenoh(config, zenoh_layer):
    """``config`` with ``zenoh_layer`` (the command line's zenoh flags) over its ``[zenoh]`` table."""
    if zenoh_layer is None or not hasattr(config, "zenoh"):
        return config
    return dataclasses.replace(config, zenoh=zenoh_layer.over(config.zenoh))


def file_kind(path: str | Path, doc: dict | None = None) -> str:
    """``"zenoh"`` (JSON5), ``"params"`` (detector parameters) or ``"service"``."""
    if str(path).endswith((".json5", ".json")):
        return "zenoh"
    doc = read_toml(path) if doc is None else doc
    return "params" if "schema" in doc or "detectors" in doc else "service"


def check_file(path: str | Path) -> str:
    """Validate any config file of the project; one line saying what it holds (ConfigError otherwise)."""
    if file_kind(path) == "zenoh":
        from mntes_stream.io.transport import ZenohSettings, describe_config, zenoh_config

        named = describe_config(zenoh_config(ZenohSettings(config_file=str(path))))
        return f"{path}: zenoh config, mode {named.get('mode')}, listen {named.get('listen/endpoints')}"
    doc = read_toml(path)
    if file_kind(path, doc) == "params":
        from mntes_stream.io.paramfile import parse_params

        params = parse_params(doc, str(path))
        return f"{path}: detector parameters, {len(params)} detectors"
    service, config = load_service_config(path)
    return f"{path}: {service.name} service config, ok"


def check_paths(paths: Iterable[str | Path]):
    """``config check``: ``(path, line, ok)`` for each config among ``paths``.

    A directory contributes its config files (``*.toml``, ``*.json5``; not
    ``*.json``, which a directory may hold for other tools, nor its
    subdirectories); a named file or directory that is not
    a config (a README, ``grafana/``) is skipped with an ok line saying so, so
    ``config check services/*`` checks exactly the configs. A missing path or a
    bad config gives ``ok`` False and the one-line reason.
    """
    for given in paths:
        path = Path(given)
        if path.is_dir():
            found = sorted(p for p in path.iterdir() if p.is_file() and p.suffix in (".toml", ".json5"))
            if not found:
                yield path, f"{path}: skipped (a directory without config files)", True
            for p in found:
                yield _checked(p)
        elif path.exists() and path.suffix not in CONFIG_SUFFIXES:
            yield path, f"{path}: skipped (not a config file: *.toml, *.json5)", True
        else:
            yield _checked(path)


def _checked(path: Path):
    try:
        return path, check_file(path), True
    except ConfigError as exc:
        return path, str(exc), False


def show_file(path: str | Path, overrides: Iterable[str] = ()) -> str:
    """The effective config, every default filled in, as TOML with each setting's doc as a comment."""
    if file_kind(path) == "zenoh":
        import json

        from mntes_stream.io.transport import ZenohSettings, describe_config, zenoh_config

        effective = describe_config(zenoh_config(ZenohSettings(config_file=str(path))))
        return "\n".join(f"{k}: {json.dumps(v)}" for k, v in effective.items())
    doc = read_toml(path)
    if file_kind(path, doc) == "params":
        from mntes_stream.io.paramfile import params_to_toml, parse_params

        return params_to_toml(list(parse_params(doc, str(path)).values()))
    service, config = load_service_config(path, overrides)
    text = render(config, service.name)
    if hasattr(config, "zenoh"):
        from mntes_stream.io.transport import describe_config, zenoh_config

        effective = describe_config(zenoh_config(config.zenoh))
        text += "\n# the zenoh session this gives (file, table and defaults layered):\n" + "\n".join(
            f"#   {k} = {toml_value(v)}" for k, v in effective.items())
    return text


def render(config, main: str) -> str:
    """A settings object as commented TOML: ``[main]`` with its own settings, then each sub-table."""
    def lines(obj, table: str) -> list[str]:
        out = [f"[{table}]"]
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name)
            s = declared(f)
            if dataclasses.is_dataclass(value):
                if s.flatten:
                    out += lines(value, table)[1:]
                continue
            text = f"# {f.name} = (not set)" if value is None else f"{f.name} = {toml_value(to_table_value(value))}"
            note = f"{s.doc} ({s.unit})" if s.unit else s.doc
            out.append(f"{text:<40s} # {note}" if note else text)
        return out

    out = lines(config, main)
    for table, field in document_tables(type(config), main).items():
        if field:
            out += [""] + lines(getattr(config, field), table)
    return "\n".join(out)


def toml_value(value: Any) -> str:
    """One TOML value on one line (arrays inline)."""
    import json
    import math

    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # a JSON string is a TOML basic string
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    raise ConfigError(f"cannot write {value!r} as TOML")


def to_table_value(value: Any) -> Any:
    """A setting's value in TOML form (tuples as lists, complex as [re, im], inf as inf)."""
    if dataclasses.is_dataclass(value):
        return to_table(value)
    if isinstance(value, (tuple, list)):
        return [to_table_value(v) for v in value]
    if isinstance(value, complex):
        return [value.real, value.imag]
    return value
