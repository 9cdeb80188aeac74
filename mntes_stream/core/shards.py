"""Which converter owns which stream: shards of a focal plane, and who publishes when two claim one.

A stream is one module's counts, ``(board, module)``. A converter run with
``shard = "i/N"`` owns the streams whose hash falls in bucket ``i`` of ``N``;
every stream belongs to exactly one bucket, whatever the order the converters
start in or the host they run on (CRC-32 of ``"<board>/<module>"``: the same on
every machine and Python, unlike ``hash()``).

Two converters may still claim one stream (two overlapping ``boards`` lists,
a hot standby). Each claim carries a :class:`Claim` rank; among the live
claims of a stream the lowest rank publishes (:func:`publisher`): the
converter that claimed first, whichever of them looks. The others hold back:
a hot standby silently (converting, ready), any other converter reporting a
conflict. When the publisher goes, the next in rank takes over.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import NamedTuple

from mntes_stream.errors import ConfigError

__all__ = ["Claim", "Shard", "StreamKey", "owned_streams", "publisher", "stream_label"]


class StreamKey(NamedTuple):
    """One stream, ``(board, module)``; written ``"<board>/<module>"`` as keys and ledgers spell it.

    A tuple (immutable; equal to, and hashed as, the plain ``(board, module)`` pairs code already keys by),
    so a parsed stream can go wherever a pair went.

    >>> k = StreamKey.parse("0/12")
    >>> k, str(k), k == (0, 12)
    (StreamKey(board=0, module=12), '0/12', True)
    >>> StreamKey.parse("0/x") is None and StreamKey.parse("other") is None
    True
    """

    board: int
    module: int

    @classmethod
    def parse(cls, text: str) -> StreamKey | None:
        """``"<board>/<module>"`` (non-negative integers) as a StreamKey; None for any other text."""
        b, sep, m = str(text).partition("/")
        return cls(int(b), int(m)) if sep and b.isdigit() and m.isdigit() else None

    def __str__(self) -> str:
        return f"{self.board}/{self.module}"


@dataclass(frozen=True)
class Shard:
    """Bucket ``index`` of ``count`` (``Shard.parse("1/3")``); ``Shard(0, 1)`` owns everything.

    >>> s = Shard.parse("1/3")
    >>> s.index, s.count, str(s)
    (1, 3, '1/3')
    >>> sum(Shard(i, 3).owns(0, 5) for i in range(3))  # exactly one shard owns a stream
    1
    """

    index: int = 0
    count: int = 1

    def __post_init__(self):
        if not (isinstance(self.count, int) and self.count >= 1 and isinstance(self.index, int)
                and 0 <= self.index < self.count):
            raise ConfigError(f"shard {self.index}/{self.count}: expected i/N with 0 <= i < N")

    @classmethod
    def parse(cls, text: str) -> Shard:
        """``"i/N"``, or ``""`` for the whole focal plane."""
        if not text:
            return cls()
        i, sep, n = str(text).partition("/")
        try:
            if not sep:
                raise ValueError
            return cls(int(i), int(n))
        except ValueError:
            raise ConfigError(f"shard {text!r}: expected i/N, e.g. 0/3") from None

    @property
    def whole(self) -> bool:
        """True for ``0/1``: every stream."""
        return self.count == 1

    def owns(self, board: int, module: int) -> bool:
        """Whether stream ``(board, module)`` is in this bucket."""
        return zlib.crc32(f"{int(board)}/{int(module)}".encode()) % self.count == self.index

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"


def owned_streams(streams: Iterable[tuple[int, int]], shard: Shard, boards: Iterable[int] = (),
                  modules: Iterable[int] = ()) -> list[tuple[int, int]]:
    """The ``(board, module)`` streams a converter owns: in ``boards`` and ``modules`` (empty: any) and its shard.

    >>> owned_streams([(0, 0), (0, 1), (1, 0)], Shard(), boards=[0])
    [(0, 0), (0, 1)]
    >>> a, b = (owned_streams([(0, m) for m in range(8)], Shard(i, 2)) for i in range(2))
    >>> sorted(a + b) == [(0, m) for m in range(8)] and not set(a) & set(b)
    True
    """
    boards, modules = set(boards), set(modules)
    return sorted((b, m) for b, m in set(streams) if (not boards or b in boards) and (not modules or m in modules)
                  and shard.owns(b, m))


def stream_label(stream: tuple[int, int]) -> str:
    """``"<board>/<module>"``, as keys spell a stream."""
    return str(StreamKey(int(stream[0]), int(stream[1])))


@dataclass(frozen=True, order=True)
class Claim:
    """One converter's claim on a stream; claims order by ``(t_claim_ns, instance)``: the earliest wins.

    ``instance`` (the claimant's zenoh id) breaks ties and tells claims of
    two processes of the same name apart. A ``standby`` claim is a planned
    second: being behind another claim is then no conflict.

    >>> a, b = Claim(10, "z1", "conv-a"), Claim(20, "z0", "conv-b")
    >>> min(a, b).name
    'conv-a'
    """

    t_claim_ns: int
    instance: str
    name: str = field(default="", compare=False)
    standby: bool = field(default=False, compare=False)


def publisher(claims: Iterable[Claim]) -> Claim | None:
    """The claim that publishes a stream: the lowest in rank among the live ones (None: nobody's).

    >>> publisher([Claim(5, "b", "standby"), Claim(3, "a", "primary")]).name
    'primary'
    >>> publisher([]) is None
    True
    """
    return min(claims, default=None)
