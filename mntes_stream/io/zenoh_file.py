"""What a zenoh JSON5 config file, or a ``KEY:VALUE`` change, names: so a built-in default never overrides it.

Read with ``json5`` (zenoh's own parser is not exposed to Python); zenoh
itself still reads the file (``zenoh.Config.from_file``) and judges its values.
"""

from __future__ import annotations

from mntes_stream.errors import ConfigError

__all__ = ["named_paths", "names_listen_endpoints"]


def named_paths(path: str) -> set[str]:
    """Every key path (``scouting/multicast/enabled`` and its parents) a zenoh JSON5 file sets."""
    import json5

    try:
        with open(path, encoding="utf-8") as f:
            doc = json5.load(f)
    except OSError as exc:
        raise ConfigError(f"zenoh config file {path}: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise ConfigError(f"zenoh config file {path}: not valid JSON5: {exc}") from None
    if not isinstance(doc, dict):
        raise ConfigError(f"zenoh config file {path}: expected an object at the top")
    out: set[str] = set()

    def walk(d: dict, prefix: str) -> None:
        for k, v in d.items():
            out.add(prefix + str(k))
            if isinstance(v, dict):
                walk(v, f"{prefix}{k}/")

    walk(doc, "")
    return out


def names_listen_endpoints(item: str) -> bool:
    """Whether a ``KEY:VALUE`` change names where to listen (``listen/timeout_ms`` does not)."""
    import json5

    key, _, value = item.partition(":")
    key = key.strip("/")
    if key.startswith("listen/endpoints"):
        return True
    if key != "listen":
        return False
    try:
        return "endpoints" in json5.loads(value)
    except (ValueError, TypeError):  # zenoh itself reports a value it cannot take
        return False
