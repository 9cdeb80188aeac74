"""What flows between the converter's stages, and the stage list that checks it (no I/O).

Each stage is a callable over a batch: it takes the batch's items in order and
returns the items it passes on, as an spt3g module takes a frame and returns
frames. It declares the item types it acts on (``takes``) and those it puts
out (``gives``); what it does not take it passes on untouched. The types:

- :class:`Received`: a received message, carried as the tuple ``(key, payload, t_recv_ns[, source])``;
- :class:`Counts` / :class:`Hk`: a decoded counts or housekeeping message;
- :class:`Tick`: a message dropped at the door, which still lets receive time pass;
- :class:`Pending`: a counts chunk booked in its stream's sequence, held for housekeeping;
- :class:`Ready`: a released chunk with its rows and housekeeping aligned;
- :class:`Run` / :class:`Converted`: a run of chunks converted in one block, or one chunk converted alone;
- :class:`Flagged`: one chunk's power with its flags complete (flagged power NaN);
- :class:`Output`: a message to publish, carried as the tuple ``(key, payload)``;
- :data:`END`, last of every batch (``End(force=True)``: flush): the stages that gather
  (housekeeping, conversion, status) act on it. Every stage passes it on.

:class:`Stages` holds the stages in order by name, and refuses, when it is
built, a stage that takes an item type no stage before it gives; a part of
the list is run by name (``span(until="encode")``), never by position.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mntes_stream.errors import ConfigError
from mntes_stream.io.messages import CountsChunk, HousekeepingChunk

__all__ = ["END", "Converted", "Counts", "End", "Flagged", "Hk", "Output", "Pending", "Ready", "Received", "Run",
           "Stages", "Tick"]


class Received:
    """Declaration only: a received message travels as the plain tuple ``(key, payload, t_recv_ns[, source])``."""


class Output:
    """Declaration only: a message to publish travels as the plain tuple ``(key, payload)``."""


@dataclass(frozen=True)
class End:
    """The end of a batch: the gathering stages act now (``force``: release everything held, a flush)."""

    force: bool = False


END = End()


@dataclass(frozen=True)
class Tick:
    """Receive time passing without an item to carry (a message dropped at the door)."""

    t_recv_ns: int


@dataclass(frozen=True)
class Counts:
    info: dict
    chunk: CountsChunk
    key: str
    t_recv_ns: int
    source: str | None = None  # the publisher (zenoh id), when the transport says it


@dataclass(frozen=True)
class Hk:
    info: dict
    hk: HousekeepingChunk
    key: str
    t_recv_ns: int


@dataclass
class Pending:
    """A counts chunk booked in its stream's sequence, waiting for its housekeeping."""

    chunk: CountsChunk
    t_recv_ns: int
    t_ns: np.ndarray
    t_last_ns: int | None
    late: bool = False  # set aside under overload: converted later, published as late power


@dataclass
class Ready:
    """A released chunk with its rows and aligned housekeeping, waiting to be converted."""

    chunk: CountsChunk
    ids: tuple
    known: np.ndarray
    n_unknown: int
    t_bath: np.ndarray
    b_field: np.ndarray
    v_bias: np.ndarray | None
    env_flags: np.ndarray
    env_flags_t: np.ndarray
    late: bool = False
    order: int = 0  # its place in the batch's release order (``Convert``), which ``Flags`` restores


@dataclass
class Run:
    """A run's converted blocks: per part, its modules and their block."""

    run: list
    orders: list
    cols: np.ndarray
    parts: list  # (m0, m1, p_opt, flags, env_flags, rows, sigma)


@dataclass
class Converted:
    """One chunk converted alone: its power, the converter's flags and sigma_P (or None)."""

    ready: Ready
    p_opt: np.ndarray
    flags: np.ndarray
    sigma: np.ndarray | None


@dataclass
class Flagged:
    """One chunk's power, flags and sigma_P with housekeeping and unknown-row flags applied (flagged power NaN)."""

    ready: Ready
    p_opt: np.ndarray
    flags: np.ndarray
    sigma: np.ndarray | None


def _names(types) -> str:
    return ", ".join(t.__name__ for t in types) or "nothing"


class Stages:
    """The stages of a pipeline in order, by name, each one's ``takes`` given by a stage before it.

    Parameters
    ----------
    stages : iterable of callables ``stage(items: list) -> list``
        Each with ``name`` (unique), ``takes`` and ``gives`` (tuples of item types).
    entry : tuple of types
        What is fed to the first stage (default: received messages).

    Raises
    ------
    ConfigError
        Two stages of one name, or a stage that takes an item type that neither
        ``entry`` nor any stage before it gives.
    """

    def __init__(self, stages, entry: tuple = (Received,)):
        self._stages = tuple(stages)
        self._index: dict[str, int] = {}
        for k, stage in enumerate(self._stages):
            if stage.name in self._index:
                raise ConfigError(f"two stages are named {stage.name!r}")
            self._index[stage.name] = k
        self.entry = tuple(entry)
        self._spans: dict[tuple, tuple] = {}
        self.span()  # the whole list, checked now

    @property
    def names(self) -> list[str]:
        return list(self._index)

    def __getitem__(self, name: str):
        return self._stages[self._position(name)]

    def __iter__(self):
        return iter(self._stages)

    def __len__(self) -> int:
        return len(self._stages)

    def _position(self, name: str) -> int:
        try:
            return self._index[name]
        except KeyError:
            raise ConfigError(f"no stage named {name!r} (stages: {', '.join(self._index)})") from None

    def span(self, first: str | None = None, until: str | None = None, entry: tuple | None = None) -> tuple:
        """The stages from ``first`` to ``until`` (both included; None: the list's ends), checked for ``entry``.

        ``entry``: the item types fed to ``first`` (default: this list's entry). Raises ConfigError as the
        constructor does. The result is kept: a span is checked once.
        """
        key = (first, until, entry)
        got = self._spans.get(key)
        if got is None:
            a = 0 if first is None else self._position(first)
            b = len(self._stages) if until is None else self._position(until) + 1
            if b <= a:
                raise ConfigError(f"stage {until!r} comes before {first!r}")
            got = self._stages[a:b]
            have = set(self.entry if entry is None else entry)
            for stage in got:
                missing = [t for t in stage.takes if t not in have]
                if missing:
                    raise ConfigError(f"stage {stage.name!r} takes {_names(missing)}, which no stage before it "
                                      f"gives (fed: {_names(self.entry if entry is None else entry)}; before it: "
                                      f"{', '.join(s.name for s in self._stages[a:self._index[stage.name]]) or 'none'})")
                have.update(stage.gives)
            self._spans[key] = got
        return got

    def replace(self, stage) -> Stages:
        """A new list with the stage of ``stage.name`` replaced by ``stage`` (checked again)."""
        k = self._position(stage.name)
        return Stages(self._stages[:k] + (stage,) + self._stages[k + 1:], self.entry)
