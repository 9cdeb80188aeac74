"""zenoh key expressions: the one place that spells them.

    mntes/<setup>/counts/<board>/<module>   counts chunks (schema mntes.counts)
    mntes/<setup>/hk/<sensor>               housekeeping   (schema mntes.hk)
    mntes/<setup>/power/<board>/<module>    power chunks   (schema mntes.power)
    mntes/<setup>/status/<service>          service status (schema mntes.status)
    mntes/<setup>/provenance                parameters + table identity (schema mntes.provenance)
    mntes/<setup>/alive/<service>/<name>    liveliness token + heartbeat queryable (io/presence.py)
    mntes/<setup>/claim/<board>/<module>/<t_claim_ns>/<instance>/<role>/<name>
                                            liveliness token: a converter claims a stream (io/claims.py)
"""

from __future__ import annotations

from mntes_stream.core.ids import NAME_PATTERN
from mntes_stream.errors import ConfigError

PREFIX = "mntes"
# The setup name every service uses unless told otherwise.
DEFAULT_SETUP = "lab"
KINDS = ("counts", "hk", "power", "status", "provenance")


def _check(name: str, what: str) -> str:
    name = str(name)
    if not NAME_PATTERN.fullmatch(name):
        raise ConfigError(f"{what} {name!r} must match [A-Za-z0-9_.-]+ (no '/', '*', '$')")
    return name


def counts_key(setup: str, board: int | str = "*", module: int | str = "*") -> str:
    return f"{PREFIX}/{_check(setup, 'setup')}/counts/{board}/{module}"


def hk_key(setup: str, sensor: str = "**") -> str:
    return f"{PREFIX}/{_check(setup, 'setup')}/hk/{sensor}"


def bias_sensor(board: int, module: int) -> str:
    """Sensor name of one module's bias readings: ``bias/<board>/<module>``."""
    return f"bias/{int(board)}/{int(module)}"


def hk_sensor(sensor: str, board: int | None = None, module: int | None = None) -> str:
    """The key's sensor part for a housekeeping message (per-channel sensors are per module:
    ``bias/<board>/<module>``, ``readout_flags/<board>/<module>``)."""
    if sensor == "bias":
        return bias_sensor(board, module)
    if sensor == "readout_flags":
        return f"readout_flags/{int(board)}/{int(module)}"
    return sensor


def power_key(setup: str, board: int | str = "*", module: int | str = "*") -> str:
    return f"{PREFIX}/{_check(setup, 'setup')}/power/{board}/{module}"


def status_key(setup: str, service: str = "*") -> str:
    return f"{PREFIX}/{_check(setup, 'setup')}/status/{service}"


def provenance_key(setup: str) -> str:
    return f"{PREFIX}/{_check(setup, 'setup')}/provenance"


def alive_key(setup: str, service: str = "*", name: str = "*") -> str:
    """A running service's liveliness token and heartbeat queryable."""
    return f"{PREFIX}/{_check(setup, 'setup')}/alive/{service}/{name}"


def claim_key(setup: str, board: int | str = "*", module: int | str = "*", t_claim_ns: int | str = "*",
              instance: str = "*", role: str = "*", name: str = "*") -> str:
    """A converter's claim on stream ``(board, module)``; ``role`` is ``primary`` or ``standby``
    (``"**"`` as board: every claim of the setup)."""
    if board == "**":
        return f"{PREFIX}/{_check(setup, 'setup')}/claim/**"
    return f"{PREFIX}/{_check(setup, 'setup')}/claim/{board}/{module}/{t_claim_ns}/{instance}/{role}/{name}"


def all_key(setup: str) -> str:
    """Everything of one setup (what the recorder subscribes to)."""
    return f"{PREFIX}/{_check(setup, 'setup')}/**"


def kind_of(key: str) -> str:
    """``counts``, ``hk``, ``power``, ``status``, ``provenance`` or ``""`` for a foreign key."""
    parts = str(key).split("/")
    if len(parts) >= 3 and parts[0] == PREFIX and parts[2] in KINDS:
        return parts[2]
    return ""


def parse_key(key: str) -> dict:
    """Split a concrete key into its parts: ``{"setup", "kind", ...}``."""
    parts = str(key).split("/")
    if len(parts) < 3 or parts[0] != PREFIX:
        raise ConfigError(f"not an mntes key: {key!r}")
    setup, kind, rest = parts[1], parts[2], parts[3:]
    out: dict = {"setup": setup, "kind": kind}
    if kind in ("counts", "power") and len(rest) == 2:
        out["board"], out["module"] = rest
    elif kind == "hk" and rest:
        out["sensor"] = "/".join(rest)
    elif kind == "status" and len(rest) == 1:
        out["service"] = rest[0]
    elif kind == "provenance" and not rest:
        pass
    else:
        raise ConfigError(f"malformed mntes key: {key!r}")
    return out
