"""One exception hierarchy for the whole package.

Validation happens at the boundary (files, messages, CLI arguments) and raises
one of these; the core never uses ``assert`` for input checking.
"""


class MntesError(Exception):
    """Root of every error raised on purpose by mntes-stream."""


class ConfigError(MntesError, ValueError):
    """Bad parameters or configuration: unknown key, missing or unphysical value."""


# Why a message was rejected: the keys of a status message's ``bad_messages``.
SCHEMA_REASONS = ("malformed", "unknown_schema", "wrong_schema", "wrong_version", "invalid", "wrong_key")


class SchemaError(MntesError, ValueError):
    """A message or file does not match its schema (name, version, fields, dtypes).

    ``reason`` is one of :data:`SCHEMA_REASONS`: the counter a rejected
    message goes to (``invalid`` unless the raiser knows better).
    """

    def __init__(self, message: str, reason: str = "invalid"):
        super().__init__(message)
        self.reason = reason if reason in SCHEMA_REASONS else "invalid"


class TableDomainError(MntesError, ValueError):
    """A request lies outside the domain a response table or model was built for."""


class TransportError(MntesError, RuntimeError):
    """zenoh or MCAP transport failure (session, key expression, truncated file)."""


class MissingExtraError(MntesError, ImportError):
    """An optional integration is not installed; the message names the extra that installs it."""


def import_extra(module: str, extra: str):
    """``importlib.import_module(module)``, or MissingExtraError naming ``pip install 'mntes-stream[extra]'``."""
    import importlib

    try:
        return importlib.import_module(module)
    except MissingExtraError:  # already says why (e.g. mntes_stream.g3: so3g refused after spt3g 1.0.2)
        raise
    except ImportError as exc:
        raise MissingExtraError(
            f"{module} is not installed ({exc}); install the extra: pip install 'mntes-stream[{extra}]'"
        ) from None
