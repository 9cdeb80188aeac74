"""The converter's core, free of zenoh: messages in, power/status messages out, through one list of stages.

The live service (``service/converter.py``) feeds it what its subscriber
receives; offline re-conversion of a recording feeds it the recorded messages
in log-time order. Both get the same outputs from the same inputs because
every decision here depends only on the messages and their receive times.

What happens to a message (``handle``):

- counts chunk: decoded and validated, checked against its key, its sequence
  number booked per ``(board, module)`` stream (``core.sequence``: lost,
  late, duplicates dropped, a restarted stream resynchronised and counted as
  ``bad_messages["seq_reset"]``, not as lost). The chunk then waits until
  every *required* housekeeping sensor has a reading at or after its last
  sample (so housekeeping is interpolated, not extrapolated) or until it has
  waited ``hk_wait_s`` of receive time, whichever first;
- housekeeping (``pipeline.housekeeping``): added to that sensor's history (``core.align.HkSeries``),
  except readings stamped more than ``hk_max_ahead_s`` ahead of the data clock
  or (bias excepted: a setting holds) more than ``hk_retention_s`` behind it,
  which are counted (``bad_messages["hk_time"]``) and dropped. The data clock
  is the receive clock minus the median delay (receive time minus ``t_pub_ns``)
  of the latest counts chunks, so a replayed old recording is judged by its own
  time. History is pruned relative to the data clock, never relative to the
  newest reading, which one bad time stamp could push anywhere;
- anything that fails to decode, or does not match its key, is counted by
  reason in the status and otherwise ignored: the service never stops on one.

A released chunk is converted with the housekeeping aligned to each sample
(``core.align``): flags HK_STALE / HK_MISSING / ENV_OUT_OF_RANGE come from
there; channels without detector parameters get UNKNOWN_CHANNEL and NaN; a
converter failure flags that chunk INVALID_INPUT and is counted, never raised.
Power is NaN wherever a flag in ``core.flags.UNUSABLE`` is set, and where
HK_STALE is (``hk_stale_power = "nan"``). Every counts chunk is booked in
``ledger`` (``core.ledger``).

The work is a list of named stages (:func:`converter_stages`), each a callable
over a batch of items in the style of an spt3g pipeline: decode, sequence,
housekeeping (with alignment), convert, flags, encode, status
(``pipeline.stages``, ``pipeline.convert``, ``pipeline.status``), each
declaring the item types it takes and gives (``pipeline.items``), checked when
the list is built. The list is declared once; the live service, offline
``convert``, replay into a converter and the G3 ``OpticalPower`` module all run
it through :class:`ConverterPipeline`, which runs parts of it by name (a
flush: ``until="encode"``; late power: ``"convert"`` to ``"encode"``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from mntes_stream.core.ledger import Ledger
from mntes_stream.errors import ConfigError
from mntes_stream.pipeline.config import SCALAR_SENSORS, PipelineConfig
from mntes_stream.pipeline.convert import Convert, Encode, Flags
from mntes_stream.pipeline.housekeeping import Housekeeping, known_modules
from mntes_stream.pipeline.items import END, End, Ready, Stages
from mntes_stream.pipeline.stages import Align, Books, Decode, Environment, PipelineCounters, Sequence
from mntes_stream.pipeline.status import Status

__all__ = ["PipelineConfig", "ConverterPipeline", "PipelineCounters", "SCALAR_SENSORS", "converter_stages"]

log = logging.getLogger("mntes_stream.converter")


def converter_stages(books: Books, converter, *, params: list, modules, owns: dict, threads: int,
                     set_aside_bytes: int, noise=None, sigma_p: bool = False, params_toml: str | None = None,
                     typed: bool = False) -> Stages:
    """The converter's stages, in order: the one declaration every path runs.

    Returns
    -------
    Stages
        ``decode, sequence, housekeeping, convert, flags, encode, status``, each
        ``stage(items: list) -> list`` (``pipeline.items``), checked as a list.
    """
    nominal = {p.detector_id: float(p.v_thev_v) for p in params}
    hk = Housekeeping(books.config, nominal, modules)
    sequence = Sequence(books, modules, set_aside_bytes)
    align = Align(books, hk, Environment(books, hk, frozenset(converter.detector_ids)))
    convert = Convert(books, converter, threads, noise, sigma_p)
    return Stages((
        Decode(books, modules),
        sequence,
        align,
        convert,
        Flags(books),
        Encode(books, str(converter.identity), str(converter.kind), typed),
        # The provenance names the noise in use now (measured live: renewed window by window).
        Status(books, sequence, align, converter, params, owns, (lambda: convert.noise) if noise else None, sigma_p,
               params_toml),
    ))


class ConverterPipeline:
    """Counts + housekeeping in, power chunks + status out (no I/O): :func:`converter_stages` run in order.

    Parameters
    ----------
    converter
        Has ``kind``, ``identity``, ``detector_ids`` and
        ``convert(detector_ids, counts_i, counts_q, env) -> PowerBlock``
        (``core.convert.make_converter``).
    config : PipelineConfig
    params : dict or list of DetectorParams, optional
        The detector parameters (provenance and nominal bias); default
        ``converter.params`` when it has them.
    params_toml : str, optional
        Their TOML text (``io.paramfile.params_to_toml``) when the caller has it already
        (a converter snapshot); default: written from ``params`` once, for the first provenance.
    clock : callable or None
        Publication time stamp of outputs (ns); default ``time.time_ns``.
        None stamps outputs with the receive time of the message being handled,
        which makes offline re-conversion reproducible.
    owns : dict, optional
        The part of the focal plane a converter shard owns, for its provenance
        (``service.ownership.owns_summary``); None: the whole of it.
    threads : int
        Threads converting a large run of chunks side by side (1: the calling
        thread alone). The power is the same whatever the number.
    set_aside_bytes : int
        Counts held at most under overload for late conversion; beyond, the
        oldest set-aside chunk is shed (counted in the ledger).
    uncertainty : core.uncertainty.UncertaintySettings, optional
        Given: LOW_RESPONSIVITY is flagged (``core.uncertainty.low_responsivity_block``: in
        the compiled "table" kernel's own pass); None: not (the power is the same).
    sigma_p : bool
        With ``uncertainty``: every power chunk carries each sample's sigma_P too
        (``core.uncertainty.sigma_p_block``, a pass about as dear as the conversion).
    only_fused : bool
        With ``uncertainty`` and without ``sigma_p``: LOW_RESPONSIVITY only where the
        converter flags it in its own pass (``fuses_low_responsivity``); elsewhere not
        (logged once), rather than a second pass (``[converter] low_responsivity = "auto"``).
    typed : bool
        The typed entry of an in-process driver (the G3 module): a counts message's payload may be the
        ``CountsChunk`` itself, not its bytes, and power comes out as ``(key, PowerChunk)``, the chunk the
        message would carry, not its bytes (status and provenance stay messages). No byte round trip.

    Attribute ``overloaded`` (False unless the live service sets it, so offline
    runs never shed): while True, a chunk further behind its stream's pace than
    ``max_lag_s`` is set aside, not converted now; :meth:`convert_late`
    converts set-aside chunks when the service has time. ``ledger``
    (``core.ledger.Ledger``) accounts for every chunk of every stream.

    Attribute ``owns_status`` (a callable returning a dict, or None) gives the
    status its ``owns``: what is owned, published and held back now.
    """

    def __init__(self, converter, config: PipelineConfig | None = None, params=None,
                 clock: Callable[[], int] | None = time.time_ns, owns: dict | None = None, threads: int = 1,
                 set_aside_bytes: int = 256 << 20, uncertainty=None, sigma_p: bool = False,
                 only_fused: bool = False, params_toml: str | None = None, typed: bool = False):
        if not isinstance(threads, int) or threads < 1:
            raise ConfigError(f"threads must be an integer >= 1, got {threads!r}")
        self.converter = converter
        self.config = config or PipelineConfig()
        self.books = Books(self.config, clock)
        if params is None:
            params = getattr(converter, "params", None)
        if isinstance(params, dict):
            params = list(params.values())
        params = list(params) if params is not None else []
        known = frozenset(converter.detector_ids)
        modules = known_modules(known)
        if modules is None and known:
            # Ids of another form than b<B>m<M>c<C> are names: they match the rows of counts chunks that carry
            # detector_ids (dfmux-bridge: the boards' names), on a stream no id says: any stream gets state.
            odd = sorted(d for d in known if known_modules([d]) is None)
            log.info("parameters: %d of %d detector ids (e.g. %r) are names, not b<board>m<module>c<channel>: they "
                     "match the rows of counts carrying those names (any stream is taken)", len(odd), len(known),
                     odd[0])
        noise = None
        if uncertainty is not None and only_fused and not sigma_p and not getattr(converter, "fuses_low_responsivity",
                                                                                  False):
            log.info("LOW_RESPONSIVITY not flagged: a %r converter would need the sigma_P pass for it (about a "
                     "conversion's cost; [converter] low_responsivity = \"on\" to have it)", converter.kind)
            uncertainty = None
        if uncertainty is not None:
            from mntes_stream.core.uncertainty import nominal_gradients
            from mntes_stream.io.noisefile import noise_model_for  # reads the measured-noise file, if one is named

            noise = noise_model_for(list(converter.params), uncertainty, nominal_gradients(converter))
        self.stages = converter_stages(self.books, converter, params=params, modules=modules, owns=dict(owns or {}),
                                       threads=threads, set_aside_bytes=set_aside_bytes, noise=noise,
                                       sigma_p=bool(sigma_p) and noise is not None, params_toml=params_toml,
                                       typed=typed)
        self._sequence: Sequence = self.stages["sequence"]
        self._align: Align = self.stages["housekeeping"]
        self._status: Status = self.stages["status"]
        self._convert: Convert = self.stages["convert"]

    # ------------------------------------------------------------------ running the stages

    def _run(self, items: list, first: str | None = None, until: str | None = None, entry: tuple | None = None,
             what: str = "batch") -> list[tuple[str, bytes]]:
        """``items`` (of the types ``entry``) through the stages ``first`` to ``until`` (by name; None: the
        list's ends) in order; the ``(key, payload)`` messages that come out."""
        for stage in self.stages.span(first, until, entry):
            try:
                items = stage(items)
            except Exception as exc:  # noqa: BLE001 - the service must survive its own bugs too
                self.books.internal(exc, getattr(stage, "name", str(stage)), what)
                items = [END]  # what the stage held is counted as its chunks' (the ledger shows them pending)
        return [item for item in items if type(item) is tuple]

    def handle(self, key: str, payload: bytes, t_recv_ns: int) -> list[tuple[str, bytes]]:
        """Process one received message; returns ``(key, payload)`` messages to publish."""
        return self.handle_many(((key, payload, t_recv_ns),))

    def handle_many(self, items) -> list[tuple[str, bytes]]:
        """Process received ``(key, payload, t_recv_ns)`` messages in order; returns the messages to publish.

        An item may carry a fourth element, its publisher (``QueueSubscriber(sources=True)``): chunks of one
        stream from two publishers side by side are then numbered apart (``core.sequence.PublisherSequences``).

        One batch through the stages: each message is decoded, booked and held
        or released as :meth:`handle` would, message by message; the released
        chunks are then converted together, so the power is the same as from
        :meth:`handle` called per message, for less work per chunk.
        """
        return self._run([tuple(item) for item in items] + [END])  # (key, payload, t_recv_ns[, source])

    def tick(self, t_now_ns: int) -> list[tuple[str, bytes]]:
        """Let time pass without a message: release chunks that waited long enough, status when due."""
        self.books.advance(int(t_now_ns))
        self._align.tick(int(t_now_ns))
        return self._run([END])

    def flush(self) -> list[tuple[str, bytes]]:
        """Convert everything still held (with what housekeeping there is) and emit a final status."""
        out = self._run([End(force=True)], until="encode", what="flush")  # one status, the final one below
        out += self.convert_late(len(self._sequence.aside))
        if self.books.now_ns is not None:
            try:
                out.append(self._status.emit())
            except Exception as exc:  # noqa: BLE001
                self.books.internal(exc, "status", "flush")
        return out

    def convert_late(self, max_chunks: int) -> list[tuple[str, bytes]]:
        """Convert up to ``max_chunks`` set-aside chunks, oldest first (each stream's in order): late power."""
        ready = []
        for p in self._sequence.take_aside(max_chunks):
            try:
                ready.append(self._align.environment(p))
            except Exception as exc:  # noqa: BLE001
                self.books.dropped(p.chunk, exc)
        if not ready:
            return []
        # Convert, flags, encode: no new status for late power alone.
        return self._run(ready + [END], "convert", "encode", (Ready,), "late")

    def resume_sequences(self, state: dict) -> int:
        """Continue streams from a previous converter's :meth:`sequence_state` (before any chunk arrives).

        A stream's first chunk then tells what was published while no converter ran: counted in
        ``chunks_lost`` and ``chunks_missed_while_down``, and said once per stream (log, ``last_error``).
        A stream that restarted meanwhile is a ``seq_reset`` as usual. Returns the streams resumed.
        """
        return self._sequence.resume(state)

    def sequence_state(self) -> dict[tuple[int, int], tuple[int, int]]:
        """A checkpoint: ``(board, module) -> (newest sequence number converted, newest first-sample time ns)``.

        Chunks still held (waiting for housekeeping, set aside) are not converted yet: the number stops below
        the oldest of them, so a restart from here converts them again instead of taking them as done.
        """
        held: dict[tuple[int, int], int] = {}
        for p in (*self._align.pending, *self._sequence.aside):
            k = (p.chunk.board, p.chunk.module)
            held[k] = min(held.get(k, p.chunk.seq), p.chunk.seq)
        return {k: (min(s.next - 1, held.get(k, s.next) - 1), s.newest_t_ns)
                for k, s in self._sequence.streams.items() if s.next is not None and s.newest_t_ns is not None}

    def ledger_now(self) -> Ledger:
        """The ledger with each stream's never-received count as its sequence tracker says now."""
        return self._sequence.ledger_now()

    def unconfirmed_before_restart(self) -> dict[tuple[int, int], tuple[int, int, int]]:
        """``(board, module) -> (first seq, last seq, chunks)``: converted by the converter before a restart
        after its last status, and not taken again from the sources' history (``Sequence.unconfirmed``)."""
        return self._sequence.unconfirmed()

    def status(self):
        """The status (``io.messages.StatusMessage``) as of the latest message."""
        return self._status.status()

    def provenance(self):
        return self._status.provenance()

    def provenance_bytes(self) -> bytes:
        return self._status.provenance_bytes()

    # ------------------------------------------------------------------ state, as the services read it

    @property
    def pending(self) -> int:
        """Chunks held back waiting for housekeeping."""
        return len(self._align.pending)

    @property
    def set_aside(self) -> int:
        """Chunks set aside under overload, waiting for :meth:`convert_late`."""
        return len(self._sequence.aside)

    @property
    def overloaded(self) -> bool:
        return self._sequence.overloaded

    @overloaded.setter
    def overloaded(self, value: bool) -> None:
        self._sequence.overloaded = bool(value)

    @property
    def owns_status(self):
        return self._status.owns_status

    @owns_status.setter
    def owns_status(self, fn) -> None:
        self._status.owns_status = fn

    @property
    def kernel_cpu_s(self) -> float:
        """CPU seconds spent inside the converter's calls so far (the kernel; summed over threads)."""
        return self._convert.kernel_cpu_s

    @property
    def chunks_per_kernel_call(self) -> float | None:
        """Chunks converted per converter call so far, on average (None before the first call)."""
        c = self._convert
        return c.kernel_chunks / c.kernel_calls if c.kernel_calls else None

    @property
    def hk(self) -> Housekeeping:
        return self._align.hk

    @property
    def counters(self) -> PipelineCounters:
        return self.books.counters

    @property
    def ledger(self) -> Ledger:
        return self.books.ledger

    @property
    def bad_messages(self):
        return self.books.bad_messages

    @property
    def flag_counts(self):
        return self.books.flag_counts

    @property
    def last_error(self) -> str:
        return self.books.last_error

    @last_error.setter
    def last_error(self, text: str) -> None:
        self.books.last_error = text
