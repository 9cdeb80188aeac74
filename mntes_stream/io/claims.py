"""Stream claims on zenoh: which converter publishes which stream (liveliness tokens, no broker).

A converter declares one liveliness token per stream it owns,
``mntes/<setup>/claim/<board>/<module>/<t_claim_ns>/<instance>/<role>/<name>``, and
watches every claim of its setup. zenoh removes a token when its session
closes or its process dies (the transport's link loss: milliseconds on a
dead local process), so every converter knows at once who claims what. Who
publishes a stream is decided by ``core.shards.publisher`` (the earliest
claim) by each claimant on its own: no election messages, and the answer is
the same everywhere once the tokens have propagated.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterable

from mntes_stream.core.shards import Claim, StreamKey, publisher
from mntes_stream.errors import TransportError
from mntes_stream.io import keys

__all__ = ["StreamClaims", "parse_claim"]

log = logging.getLogger(__name__)


def parse_claim(key: str) -> tuple[StreamKey, Claim] | None:
    """``((board, module), Claim)`` of a claim token's key; None for anything else."""
    parts = str(key).split("/")
    if len(parts) != 9 or parts[0] != keys.PREFIX or parts[2] != "claim":
        return None
    try:
        return StreamKey(int(parts[3]), int(parts[4])), Claim(int(parts[5]), parts[6], parts[8], parts[7] == "standby")
    except ValueError:
        return None


class StreamClaims:
    """This converter's claims on ``streams`` and everyone's claims on them, kept current by zenoh.

    Parameters
    ----------
    session : zenoh.Session
    setup, name : str
    streams : iterable of (board, module)
        The streams this converter owns.
    standby : bool
        Claim as a hot standby (a planned second, no conflict).
    t_claim_ns : int, optional
        Rank of the claim (default: now): the earliest claim of a stream publishes it.
    settle_s : float
        How long to wait for the claims already on the network before deciding anything.

    ``version`` changes whenever a claim on one of ``streams`` appears or goes,
    so a caller re-reads :meth:`publishing` only then.
    """

    def __init__(self, session, setup: str, name: str, streams: Iterable[tuple[int, int]], standby: bool = False,
                 t_claim_ns: int | None = None, settle_s: float = 3.0):
        self.streams = frozenset(streams)
        self.me = Claim(int(t_claim_ns if t_claim_ns is not None else time.time_ns()), str(session.zid()), name,
                        bool(standby))
        self._lock = threading.Lock()
        self._others: dict[tuple[int, int], set[Claim]] = {s: set() for s in self.streams}
        self.version = 0
        self._tokens = []
        self._sub = None
        liveliness = session.liveliness()
        selector = keys.claim_key(setup, "**")
        try:
            # The claims already there, before this converter decides anything: a query returns them now.
            # Then the subscriber (its history covers a claim made in between). In this order: a callback
            # subscriber delivering its history while this thread waits on the query's replies deadlocks.
            import zenoh

            # zenoh's default reply channel is bounded: a setup with more claims than it holds would never
            # finish the query. Every claim of the setup fits this one.
            replies = zenoh.handlers.FifoChannel(max(1 << 16, 8 * len(self.streams)))
            for reply in liveliness.get(selector, replies, timeout=settle_s):
                if reply.ok is not None:
                    self._change(str(reply.ok.key_expr), alive=True)
            self._sub = liveliness.declare_subscriber(selector, self._on_sample, history=True)
            for b, m in sorted(self.streams):
                self._tokens.append(liveliness.declare_token(
                    keys.claim_key(setup, b, m, self.me.t_claim_ns, self.me.instance,
                                   "standby" if standby else "primary", name)))
        except Exception as exc:
            self.close()
            raise TransportError(f"cannot declare stream claims on {selector}: {exc}") from None

    def _on_sample(self, sample) -> None:
        import zenoh

        self._change(str(sample.key_expr), alive=sample.kind != zenoh.SampleKind.DELETE)

    def _change(self, key: str, alive: bool) -> None:
        parsed = parse_claim(key)
        if parsed is None:
            return
        stream, claim = parsed
        if claim.instance == self.me.instance or stream not in self.streams:
            return
        with self._lock:
            held = self._others[stream]
            if alive and claim not in held:
                held.add(claim)
            elif not alive and claim in held:
                held.discard(claim)
            else:
                return
            self.version += 1

    def others(self) -> dict[tuple[int, int], list[Claim]]:
        """The other live claims on each of this converter's streams (streams nobody else claims: absent)."""
        with self._lock:
            return {s: sorted(c) for s, c in self._others.items() if c}

    def publishing(self) -> frozenset[tuple[int, int]]:
        """The streams this converter publishes now: those where its claim is the earliest live one."""
        with self._lock:
            return frozenset(s for s, c in self._others.items() if publisher(c | {self.me}) == self.me)

    def close(self) -> None:
        """Withdraw the claims (others take over at once) and stop watching."""
        for token in self._tokens:
            try:
                token.undeclare()
            except Exception:  # the session is already closing: zenoh drops the tokens with it
                pass
        self._tokens.clear()
        if self._sub is not None:
            try:
                self._sub.undeclare()
            except Exception:
                pass
            self._sub = None
