"""Streaming benchmark: source -> zenoh -> converter -> zenoh -> recorder (MCAP), on this machine.

Four spawned processes, zenoh peers on 127.0.0.1: the minimal physics source,
the converter service, the MCAP recorder, and a plain subscriber for the
yardstick. Two phases in one run:

1. passthrough: the source publishes pre-encoded counts chunks flat out to the
   plain subscriber, which decodes each one: what zenoh + msgpack carry with
   no conversion (``passthrough_msamples_per_s``); then, for ``--relay-s``, the
   same chunks to a relay (:class:`_Relay`), a converter whose conversion costs
   nothing: it receives and decodes each counts chunk as the converter does and
   publishes a pre-encoded power message of the converter's size and shape for
   it, which the plain subscriber counts. The relay's M samples per CPU second
   of its own (``relay_msamples_per_core_s``) is the most a converter on this
   transport can do per core; ``converter_ratio_to_relay`` says how far the
   converter is from it;
2. stream: ``--duration`` seconds of the array in real time (or flat out with
   ``--flat-out``) through the converter into the recorder. Figures come from
   the recording itself: every power chunk's latency (``t_pub_ns`` of the
   power minus ``t_pub_ns`` of its counts chunk, both stamped at publication),
   and chunks lost = counts chunks sent minus power chunks recorded. The first
   ``--warmup`` seconds are left out of rates and latencies, not of counts.
"""

from __future__ import annotations

import os
import statistics
import struct
import tempfile
import time
from pathlib import Path

from mntes_stream.options import add_zenoh_args, zenoh_layer
from mntes_stream.service.base import Service

HELP = "source -> zenoh -> converter -> zenoh -> MCAP recorder: sustained rate, latency, loss"


def add_arguments(p) -> None:
    p.add_argument("--modules", type=int, default=40, help="readout modules (default 40)")
    p.add_argument("--channels", type=int, default=128, help="channels per module (default 128)")
    p.add_argument("--sample-rate", type=float, default=200.0, metavar="HZ", help="default 200")
    p.add_argument("--chunk-s", type=float, default=0.1, help="chunk length (default 0.1 s)")
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="seconds of data in the stream phase (default 20; 60 with --flat-out, where 20 s of data "
                        "pass in about two and the rate would be mostly start-up)")
    p.add_argument("--warmup", type=float, default=2.0, metavar="S", help="left out of rates and latencies (default 2 s)")
    p.add_argument("--passthrough-s", type=float, default=3.0, metavar="S", help="passthrough phase length (default 3 s)")
    p.add_argument("--relay-s", type=float, default=2.0, metavar="S",
                   help="after the passthrough, this long through the relay (a zero-cost converter: receive, "
                        "decode, publish a pre-encoded power message) to the same subscriber (default 2 s; 0: none)")
    p.add_argument("--kind", default="table", help="conversion kind (default table)")
    p.add_argument("--flat-out", action="store_true", help="stream phase as fast as possible instead of real time")
    p.add_argument("--threads", type=int, default=1, metavar="N",
                   help="the converter's conversion threads ([converter] threads, default 1)")
    p.add_argument("--recorder-shards", type=int, default=1, metavar="K",
                   help="K recorder processes, each recording its shard of the streams (default 1)")
    p.add_argument("--compression", default=None, choices=("zstd", "lz4", "none"),
                   help="recorder chunk compression (default: the recorder's own, lz4)")
    p.add_argument("--keep", metavar="DIR", help="keep the recording and parameters in DIR")
    p.add_argument("--repeat", type=int, default=1, metavar="N",
                   help="N runs, one after another: the figures of the last, and under \"repeat\" each run's and "
                        "the median of the per-chunk CPU figures and ratios (single runs scatter by +-15 %% on a "
                        "shared host; default 1)")
    p.add_argument("--find-rate", action="store_true",
                   help="then find the real-time rate: the highest offered rate (by sample rate) sustained for "
                        "--sustain s with 0 lost, 0 shed, 0 late and p99 latency < --p99-ms, recorder on "
                        "(a bisection, one fresh set of processes per trial; progress on stderr)")
    p.add_argument("--sustain", type=float, default=60.0, metavar="S",
                   help="--find-rate: seconds each trial rate must be sustained (default 60)")
    p.add_argument("--p99-ms", type=float, default=100.0, metavar="MS", help="--find-rate: p99 latency limit (default 100)")
    p.add_argument("--budget-s", type=float, default=900.0, metavar="S",
                   help="--find-rate: wall-clock budget of the search; no trial starts that would not end within "
                        "it (default 900)")
    p.add_argument("--trials", type=int, default=8, metavar="N", help="--find-rate: at most N trials (default 8)")
    p.add_argument("--tolerance", type=float, default=0.1, metavar="F",
                   help="--find-rate: stop once the highest passing and lowest failing rates are within this "
                        "fraction (default 0.1)")
    add_zenoh_args(p)


class _Tally:
    """Messages and samples a subscriber took in, and when the first and last arrived (receive times)."""

    def __init__(self):
        self.n = self.samples = 0
        self.t_first = self.t_last = None

    def add(self, samples: int, t_recv_ns: int) -> None:
        self.n += 1
        self.samples += samples
        self.t_first = t_recv_ns if self.t_first is None else self.t_first
        self.t_last = t_recv_ns

    def result(self) -> dict:
        span = (self.t_last - self.t_first) / 1e9 if self.n > 1 else 0.0
        return {"messages": self.n, "samples": self.samples, "span_s": span, "t_first_ns": self.t_first,
                "t_last_ns": self.t_last, "msamples_per_s": self.samples / span / 1e6 if span > 0 else 0.0}


class _Sink(Service):
    """Plain subscriber: decode every counts chunk, count samples (the passthrough yardstick).

    ``config``: a dict with ``zenoh`` (ZenohSettings), ``key`` (the counts key expression) and optionally
    ``power_key`` (the relay's power: unpacked, its schema checked and its samples counted, reported
    under ``"relayed"``).
    """

    name = "bench-sink"
    Config = dict

    def zenoh_settings(self):
        return self.config["zenoh"]

    def setup(self, ctx) -> None:
        from mntes_stream.io.transport import QueueSubscriber

        keys = [self.config["key"], *([self.config["power_key"]] if self.config.get("power_key") else [])]
        self._sub = QueueSubscriber(ctx.session, keys, maxsize=1 << 16)
        self._counts, self._power = _Tally(), _Tally()

    def step(self, ctx) -> bool:
        from mntes_stream.io.message_base import unpack_payload
        from mntes_stream.io.messages import CountsChunk, PowerChunk

        item = self._sub.get(timeout_s=0.05)
        while item is not None:
            if "/power/" in item[0]:
                # Unpacked, not validated: the relay's messages are a converter's, and this subscriber's
                # time is not what the relay phase measures (it only must keep up).
                shape = unpack_payload(item[1], PowerChunk.SCHEMA)["p_opt_w"]["shape"]
                self._power.add(shape[0] * shape[1], item[2])
            else:
                self._counts.add(CountsChunk.from_bytes(item[1]).counts_i.size, item[2])
            item = self._sub.get()
        return True

    def counters(self) -> dict:
        return {"messages": self._counts.n if hasattr(self, "_counts") else 0}

    def finish(self, ctx) -> dict:
        self._sub.close()
        return {**self._counts.result(), "relayed": self._power.result()}


class _Relay(Service):
    """A converter whose conversion costs nothing: the ceiling of a converter's rate per core on this transport.

    It receives counts chunks as the converter does (the callback queue bounded in count and bytes as the
    converter's, each sample's publisher read, recovering subscriber, the lean decoder of the converter's
    hot path), and publishes for each a power message of the size
    and shape the converter would publish for it, encoded once per stream by the converter's encoder
    (zeros for power and flags); per chunk only the two publication times at the end of the message
    are stamped anew (fixed-width integers: a slice and a pack). Publishers keep the converter's
    history cache. ``config``: a dict with ``zenoh``, ``key`` (counts key expression), ``setup`` (of
    the power keys).
    """

    name = "bench-relay"
    Config = dict

    def zenoh_settings(self):
        return self.config["zenoh"]

    def history_chunks(self) -> int:
        from mntes_stream.io.history import POWER_CHUNK_S, cache_chunks

        return cache_chunks(self.config["zenoh"].history_seconds, POWER_CHUNK_S)

    def setup(self, ctx) -> None:
        import dataclasses

        from mntes_stream.io.lean import CountsDecoder, PowerEncoder
        from mntes_stream.io.transport import QueueSubscriber
        from mntes_stream.service.converter import ConverterConfig

        # Received as the converter receives (service/converter.py): bounded in count and in bytes (a relay
        # behind the source pushes back on it instead of piling up), each sample's publisher read.
        conv = {f.name: f.default for f in dataclasses.fields(ConverterConfig)}  # its defaults
        self._sub = QueueSubscriber(ctx.session, [self.config["key"]], maxsize=conv["queue_size"], stop=ctx.stop,
                                    mode="callback", max_bytes=int(conv["queue_mb"] * 1e6), recover="history",
                                    sources=True)
        self._decoder = CountsDecoder()
        self._encoder = PowerEncoder(self.config["setup"], "relay", "relay")
        self._templates: dict = {}  # counts key -> (power key, message head up to source_t_pub_ns, middle)
        self._tally = _Tally()

    def step(self, ctx) -> bool:
        pubs, decode, templates, setup = ctx.publishers, self._decoder.decode, self._templates, self.config["setup"]
        item = self._sub.get(timeout_s=0.05)
        while item is not None:
            key, payload = item[0], item[1]
            chunk = decode(key, payload)
            t = templates.get(key)
            if t is None:
                t = templates[key] = _relay_template(self._encoder, setup, chunk)
            pubs.put(t[0], _stamped(t, chunk.t_pub_ns, time.time_ns()))
            self._tally.add(chunk.counts_i.size, time.time_ns())
            item = self._sub.get()
        return True

    def counters(self) -> dict:
        return {"relayed": self._tally.n if hasattr(self, "_tally") else 0}

    def finish(self, ctx) -> dict:
        self._sub.close()
        return self._tally.result()


_MID = b"\xa8t_pub_ns\xcf"  # between the two times of a power message: the key t_pub_ns, its value's type byte
_U64 = struct.Struct(">Q").pack


def _relay_template(encoder, setup: str, chunk) -> tuple:
    """The relay's power message for ``chunk``'s stream: ``(power key, bytes up to source_t_pub_ns's value, middle)``.

    Encoded by the converter's :class:`~mntes_stream.io.lean.PowerEncoder` (zeros for power and flags,
    shape (n_ch, n_samp) of the chunk). Publication times since 1970 in ns pack as msgpack uint64
    (0xcf and 8 bytes), so stamping others (:func:`_stamped`) keeps the message's length and layout;
    a message not ending so raises :class:`SchemaError`.
    """
    import numpy as np

    from mntes_stream.errors import SchemaError
    from mntes_stream.io import keys

    shape = chunk.counts_i.shape
    big = (1 << 63) - 1
    msg = encoder.encode(chunk, np.zeros(shape), np.zeros(shape, np.uint16), t_pub_ns=big)
    if not msg.endswith(b"\xcf" + _U64(chunk.t_pub_ns) + _MID + _U64(big)):
        raise SchemaError(f"bench relay: the power message of stream {chunk.board}/{chunk.module} does not end "
                          "with its two publication times", "malformed")
    return keys.power_key(setup, chunk.board, chunk.module), msg[:-26], _MID


def _stamped(template: tuple, source_t_pub_ns: int, t_pub_ns: int) -> bytes:
    """The template's message with these two publication times (the rest as encoded once)."""
    return b"".join((template[1], _U64(source_t_pub_ns), template[2], _U64(t_pub_ns)))


class BenchSource(Service):
    """The minimal source of ``bench stream`` and ``bench scale``: an optional passthrough phase, then the array.

    ``config`` is a dict: ``source`` (SourceConfig), ``params`` (file), ``zenoh``, ``duration_s`` (of data),
    and optionally ``flat_out`` (default True), ``passthrough_s`` with ``pass_setup`` (phase 1: the same
    counts messages re-keyed to ``pass_setup``, flat out, for a plain subscriber), then ``relay_s`` with
    ``relay_setup`` (the same, re-keyed to ``relay_setup``, for the relay), ``match_s`` (how long
    the counts may wait for their subscriber, default 60), ``settle_s`` (a pause before the clock starts,
    default 0.5) and ``label`` (for its errors). After the last batch it stays until stopped: ``put``
    returns once a message is queued, not delivered, and closing the session would lose what the
    converter has not taken yet.
    """

    name = "bench-source"
    Config = dict

    def zenoh_settings(self):
        return self.config["zenoh"]

    def duration_s(self) -> float:
        return 0.0  # ``duration_s`` is of data; the run ends when the bench stops it

    def setup(self, ctx) -> None:
        from mntes_stream.io import keys
        from mntes_stream.io.paramfile import load_params
        from mntes_stream.service.source import MinimalSource

        cfg = self.config
        self._src = MinimalSource(cfg["source"], list(load_params(cfg["params"]).values()))
        self._src.prepare()
        sc = cfg["source"]
        self._counts_keys = [keys.counts_key(sc.setup, b, m) for b in range(sc.boards) for m in range(sc.modules)]
        self._out: dict = {}
        self._n_batches = 0
        self._work = self._phases(ctx)

    def _phases(self, ctx):
        """The run as a generator: each ``next`` is one unit of work (one :meth:`step`)."""
        from mntes_stream.errors import TransportError
        from mntes_stream.service.source import Pacer

        cfg, src, pubs = self.config, self._src, ctx.publishers
        sc = cfg["source"]
        if cfg.get("passthrough_s", 0) > 0:
            counts = [(k, p) for _, batch in src.batches(time.time_ns(), duration_s=2.0) for k, p in batch
                      if "/counts/" in k]
            phases = [("passthrough", cfg["pass_setup"], cfg["passthrough_s"])]
            if cfg.get("relay_s", 0) > 0:
                phases.append(("relay", cfg["relay_setup"], cfg["relay_s"]))
            for phase, setup, seconds in phases:
                msgs = [(k.replace(f"/{sc.setup}/", f"/{setup}/", 1), p) for k, p in counts]
                pubs.wait_matching(sorted({k for k, _ in msgs}), 30.0, ctx.stop)
                yield
                n = 0
                t_end = time.monotonic() + seconds
                while time.monotonic() < t_end:
                    for k, p in msgs:
                        pubs.put(k, p)
                    n += len(msgs)
                    yield
                self._out[f"{phase}_sent"] = n
        match_s = float(cfg.get("match_s", 60.0))
        if not pubs.wait_matching(self._counts_keys, match_s, ctx.stop):
            raise TransportError(f"{cfg.get('label', 'bench stream')}: the converter did not subscribe to every "
                                 f"counts stream within {match_s:g} s")
        yield
        ctx.stop.wait(float(cfg.get("settle_s", 0.5)))  # what came before drains; shards settle
        start = time.time_ns()
        self._out["t_start_ns"] = start
        self._pacer = Pacer(0.0 if cfg.get("flat_out", True) else 1.0, start)
        m0, b0 = pubs.messages, pubs.bytes
        for t_pub_ns, batch in src.batches(start, cfg["duration_s"]):
            self._pacer.wait(t_pub_ns, ctx.stop)
            for key, payload in batch:
                pubs.put(key, payload)
            self._n_batches += 1
            self._out.update(messages=pubs.messages - m0, bytes=pubs.bytes - b0)
            yield
        self._out["t_end_ns"] = time.time_ns()
        while True:  # stay until stopped (see the class docstring)
            ctx.stop.wait(0.05)
            yield

    def step(self, ctx) -> bool:
        return next(self._work, False) is None

    def counters(self) -> dict:
        return {"batches": getattr(self, "_n_batches", 0)}

    def finish(self, ctx) -> dict:
        out = dict(self._out, batches=self._n_batches, chunks_sent=self._n_batches * len(self._counts_keys))
        if "t_start_ns" in out:
            out.setdefault("t_end_ns", time.time_ns())  # stopped while publishing
            out["behind_max_ms"] = self._pacer.behind_max_ms
        return out


STALL_S = 60.0  # without every chunk, this long without the converter's progress ends a run


def _steps(duration_s: float, rate_hz: float, n: int) -> int:
    """Readout steps in ``duration_s`` of data, counted as ``MinimalSource.batches`` counts them."""
    step = 0
    while round(step * n * 1e9 / rate_hz) < duration_s * 1e9:
        step += 1
    return step


def _analyse(rec_dir: Path, setup: str, t_start_ns: int, warmup_s: float, window_end_ns: int | None):
    from mntes_stream.io.mcap import iter_messages
    from mntes_stream.io.messages import PowerChunk

    lat_ms, seen = [], set()
    counts = power = samples_window = 0
    t_first = t_last = None
    t_from = t_start_ns + int(warmup_s * 1e9)
    for m in iter_messages(rec_dir):
        if f"/{setup}/counts/" in m.topic:
            counts += 1
        elif f"/{setup}/power/" in m.topic:
            pw = PowerChunk.from_bytes(m.payload)
            power += 1
            seen.add((pw.board, pw.module, pw.seq))
            if pw.source_t_pub_ns >= t_from and (window_end_ns is None or pw.source_t_pub_ns < window_end_ns):
                lat_ms.append((pw.t_pub_ns - pw.source_t_pub_ns) / 1e6)
                samples_window += pw.p_opt_w.size
                t_first = pw.t_pub_ns if t_first is None else min(t_first, pw.t_pub_ns)
                t_last = pw.t_pub_ns if t_last is None else max(t_last, pw.t_pub_ns)
    return lat_ms, len(seen), power, counts, samples_window, t_first, t_last


def _cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of a live process so far (Linux /proc); None where unreadable."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            stat = f.read().rsplit(")", 1)[1].split()
        return (int(stat[11]) + int(stat[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def _rss_mb(pid: int) -> float | None:
    """Resident memory of a live process in MiB, as ``process_max_rss_mb`` (Linux /proc); None where unreadable."""
    try:
        with open(f"/proc/{pid}/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return None


def _rss_growth(samples: list, t0_ns: int, t1_ns: int) -> dict:
    """Per process: resident MB at the start, middle and end of ``[t0_ns, t1_ns]``, and the growth in each half.

    ``samples`` are ``(t_ns, {name: rss_mb})``; each point is the last sample at or before it.
    """
    def at(t_ns):
        before = [s for s in samples if s[0] <= t_ns]
        return before[-1][1] if before else {}

    a, b, c = at(t0_ns), at((t0_ns + t1_ns) // 2), at(t1_ns)
    out = {}
    for name in c:
        x, y, z = a.get(name), b.get(name), c.get(name)
        if None in (x, y, z):
            continue
        out[name] = {"start": round(x), "middle": round(y), "end": round(z),
                     "first_half": round(y - x), "second_half": round(z - y)}
    return out


def _cpu_used(samples: list, t0_ns: int | None, t1_ns: int | None) -> tuple[float, dict]:
    """Wall seconds and each process's CPU seconds between two wall-clock times, from ``(t_ns, {name: cpu_s})``.

    The first and last samples inside the window bound it (wall 0 and ``{}`` when fewer than two).
    """
    if t0_ns is None or t1_ns is None:
        return 0.0, {}
    inside = [s for s in samples if t0_ns <= s[0] <= t1_ns]
    if len(inside) < 2:
        return 0.0, {}
    (ta, a), (tb, b) = inside[0], inside[-1]
    return (tb - ta) / 1e9, {k: b[k] - a[k] for k in a if a[k] is not None and b.get(k) is not None}


def _cpu_in(samples: list, t0_ns: int | None, t1_ns: int | None) -> dict:
    """Cores each process used between two wall-clock times (CPU seconds per wall second)."""
    wall, used = _cpu_used(samples, t0_ns, t1_ns)
    return {k: round(v / wall, 3) for k, v in used.items()} if wall > 0 else {}


def _per_process(samples: list, t0_ns, t1_ns, msamples_per_s: float, handled: dict) -> dict:
    """Per process over a window: CPU seconds, cores, and M samples per CPU second of what it handled.

    ``handled`` maps a process name to the fraction of the window's samples that
    went through it (a recorder shard records its share); a process not named
    there (idle in this phase) gets no rate.
    """
    wall, used = _cpu_used(samples, t0_ns, t1_ns)
    out = {}
    for name, cpu in used.items():
        share = handled.get(name)
        # msamples_per_s x wall = the samples of the window; per CPU second of this process
        rate = msamples_per_s * share * wall / cpu if share and cpu > 0 else None
        out[name] = {"cpu_s": round(cpu, 3), "cores": round(cpu / wall, 3) if wall > 0 else None,
                     "msamples_per_cpu_s": round(rate, 3) if rate else None}
    return out


# The figures ``--repeat`` gives per run and as medians (rates, per-chunk CPU, ratios), and per run and summed
# (what went missing: a loss in any run counts, not its median).
MEDIANS = ("msamples_per_s", "converter_cpu_us_per_chunk", "converter_kernel_us_per_chunk",
           "converter_chunks_per_kernel_call", "relay_cpu_us_per_chunk",
           "converter_overhead_per_relay", "converter_ratio_to_relay")
TOTALS = ("lost", "converter_shed")


def repeated(runs: list[dict]) -> dict:
    """``--repeat``'s summary of several runs' results: each figure per run, medians and totals over them
    (a figure some run lacks, e.g. a run too short to sample its CPU, has no median)."""
    per_run = {key: [r.get(key) for r in runs] for key in (*MEDIANS, *TOTALS, "stalled_s")}

    def numbers(v):
        return v and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)

    return {"runs": len(runs), "per_run": per_run,
            "median": {key: statistics.median(per_run[key]) for key in MEDIANS if numbers(per_run[key])},
            "total": {key: sum(per_run[key]) for key in TOTALS if numbers(per_run[key])}}


def run(args) -> dict:
    """One run (passthrough, then the stream phase), or ``--repeat`` runs; with ``--find-rate`` then the search for
    the real-time rate."""
    import sys

    from mntes_stream.errors import ConfigError

    n = args.repeat
    if n < 1:
        raise ConfigError("--repeat takes a count >= 1")
    runs = []
    for k in range(n):
        if n > 1:
            print(f"bench stream: run {k + 1} of {n}", file=sys.stderr, flush=True)
        runs.append(run_once(args))
    out = runs[-1]
    if n > 1:
        out["repeat"] = repeated(runs)
    if args.find_rate:
        from mntes_stream.bench._stream_rate import find_rate

        out["real_time"] = find_rate(args, out, run_once)
    return out


def run_once(args) -> dict:
    """Start the processes, run both phases (the passthrough only when ``args.passthrough_s`` > 0), measure."""
    from mntes_stream.errors import ConfigError, TransportError
    from mntes_stream.io import keys
    from mntes_stream.io.messages import StatusMessage
    from mntes_stream.io.paramfile import dump_params
    from mntes_stream.io.transport import QueueSubscriber, free_tcp_port, loopback, open_session
    from mntes_stream.service.converter import ConverterConfig
    from mntes_stream.service.recorder import RecorderConfig
    from mntes_stream.service.source import MinimalSource, SourceConfig
    from mntes_stream.service.supervise import Services

    setup, pass_setup, relay_setup = "bench", "benchpass", "benchrelay"
    if args.duration is None:
        args.duration = 60.0 if args.flat_out else 20.0
    if args.recorder_shards < 1:
        raise ConfigError("--recorder-shards takes a count >= 1")
    with_pass = args.passthrough_s > 0
    with_relay = with_pass and getattr(args, "relay_s", 0) > 0  # bench scale's arguments have no relay
    if args.compression is None:
        args.compression = RecorderConfig().compression
    n = max(1, round(args.chunk_s * args.sample_rate))
    sc = SourceConfig(setup=setup, boards=1, modules=args.modules, channels=args.channels,
                      sample_rate_hz=args.sample_rate, chunk_s=args.chunk_s, hk_interval_s=n / args.sample_rate,
                      cycle_s=1.0)
    tmp = None
    if args.keep:
        work = Path(args.keep)
        work.mkdir(parents=True, exist_ok=True)
    else:
        tmp = tempfile.TemporaryDirectory(prefix="mntes-bench-stream-")
        work = Path(tmp.name)
    rec_dir = work / "recordings"
    params_file = work / "params.toml"
    dump_params(MinimalSource(sc).params, params_file)
    p_recs = [free_tcp_port() for _ in range(args.recorder_shards)]
    p_conv, p_src, p_sink, p_relay = (free_tcp_port() for _ in range(4))
    zenoh = zenoh_layer(args)
    rec_cfgs = [RecorderConfig(setup=setup, directory=str(rec_dir), flush_interval_s=1.0, rotate_s=0,
                               log_interval_s=3600, compression=args.compression,
                               shard=f"{i}/{args.recorder_shards}" if args.recorder_shards > 1 else "",
                               zenoh=zenoh.over(loopback(p))) for i, p in enumerate(p_recs)]
    rec_names = [f"recorder{i}" if i else "recorder" for i in range(len(rec_cfgs))]
    conv_cfg = ConverterConfig(setup=setup, params=str(params_file), kind=args.kind, provenance_interval_s=0,
                               threads=args.threads,
                               zenoh=zenoh.over(loopback(p_conv, p_recs)))
    peers = [p_conv, *p_recs, *([p_sink] if with_pass else []), *([p_relay] if with_relay else [])]
    src_cfg = {"source": sc, "params": str(params_file), "zenoh": zenoh.over(loopback(p_src, peers)),
               "pass_setup": pass_setup, "passthrough_s": args.passthrough_s, "duration_s": args.duration,
               "relay_setup": relay_setup, "relay_s": args.relay_s if with_relay else 0.0,
               "flat_out": args.flat_out, "label": "bench stream"}
    sink_cfg = {"zenoh": zenoh.over(loopback(p_sink)), "key": keys.counts_key(pass_setup, "*", "*"),
                "power_key": keys.power_key(relay_setup, "*", "*") if with_relay else None}
    relay_cfg = {"zenoh": zenoh.over(loopback(p_relay, [p_sink])), "key": keys.counts_key(relay_setup, "*", "*"),
                 "setup": relay_setup}
    load_before = os.getloadavg()[0]
    services = Services()
    names = ("source", "converter", *rec_names, *(["sink"] if with_pass else []), *(["relay"] if with_relay else []))
    try:
        for name, rec_cfg in zip(rec_names, rec_cfgs):
            services.start(name, "recorder", rec_cfg)
        services.start("converter", "converter", conv_cfg)
        if with_pass:
            services.start("sink", _Sink, sink_cfg)
        if with_relay:
            services.start("relay", _Relay, relay_cfg)
        services.start("source", BenchSource, src_cfg)
        deadline = time.monotonic() + args.passthrough_s + args.duration * (1 if not args.flat_out else 10) + 120
        expected = _steps(args.duration, args.sample_rate, n) * args.modules  # counts chunks the source will send
        pids = {name: proc.pid for name, proc in services.procs.items()}
        cpu_samples = []  # (wall ns, CPU seconds of each process so far): what each used in each phase
        rss_samples = []  # (wall ns, resident MB of each process): growth in each half of the stream
        with open_session(zenoh.over(loopback(None, [p_conv]))) as z:
            sub = QueueSubscriber(z, [keys.status_key(setup, conv_cfg.name)])
            # The source keeps its session open after publishing (queued is not delivered): wait
            # until the converter has received every chunk, holds nothing and has made no progress
            # for 4.5 s. Its power went out before that, so the recorder has had as long to take it in.
            # Short of every chunk, only a stall of STALL_S ends the wait (a host stalled for seconds,
            # e.g. writing back a cold disk, is not a loss), and the result says so (``stalled_s``).
            received, pending, last_change = 0, 0, time.monotonic()
            while time.monotonic() < deadline and services.alive():
                if time.monotonic() - last_change >= (4.5 if received >= expected else STALL_S):
                    break
                t_ns = time.time_ns()
                cpu_samples.append((t_ns, {name: _cpu_s(pid) for name, pid in pids.items()}))
                rss_samples.append((t_ns, {name: _rss_mb(pid) for name, pid in pids.items()}))
                item = sub.get(timeout_s=0.1)
                n_in = received
                if item is not None:
                    st = StatusMessage.from_bytes(item[1])
                    n_in, pending = st.chunks_received, st.chunks_pending
                if n_in != received or received == 0 or pending:
                    last_change = time.monotonic()
                received = n_in
            # Short of every chunk (a stall, the deadline, a service gone): how long without progress.
            stalled = round(time.monotonic() - last_change, 1) if received < expected else None
            sub.close()
        stopped = {name: services.stop(name) for name in names}  # source first: the others drain after it
    finally:
        for name in names:
            services.stop(name, timeout_s=10)
    results, ok_all = services.collect()
    src, conv, rec, sink, relay = (results.get(k, {}) for k in ("source", "converter", "recorder", "sink", "relay"))
    if not isinstance(src, dict) or "t_start_ns" not in src:
        raise TransportError(f"bench stream: the source failed: {src}; converter: {conv}; recorder: {rec}")
    window_end = None if args.flat_out else src["t_start_ns"] + int(args.duration * 1e9)
    lat, unique_power, power_msgs, counts_msgs, samples_window, t_first, t_last = _analyse(
        rec_dir, setup, src["t_start_ns"], args.warmup, window_end)
    if args.flat_out:
        span = (t_last - src["t_start_ns"]) / 1e9 if t_last else 0.0
        msps = unique_power * args.channels * n / span / 1e6 if span > 0 else 0.0
    else:
        span = args.duration - args.warmup
        msps = samples_window / span / 1e6 if span > 0 else 0.0
    q = statistics.quantiles(lat, n=100, method="inclusive") if len(lat) >= 2 else [float("nan")] * 99
    # Cores each process used while the stream was converted, and while the passthrough ran: flat out on
    # a small host they share the cores, so a rate alone does not say which process set it.
    stream_end = t_last if args.flat_out else src["t_end_ns"]
    sink = sink if isinstance(sink, dict) else {}
    pass_msps = sink.get("msamples_per_s", 0.0)
    # Every stream sample goes through the source, the converter and (its share) each recorder shard.
    share = {"source": 1.0, "converter": 1.0, **{name: 1.0 / len(rec_names) for name in rec_names}}
    procs_stream = _per_process(cpu_samples, src["t_start_ns"], stream_end, msps, share)
    procs_pass = _per_process(cpu_samples, sink.get("t_first_ns"), sink.get("t_last_ns"), pass_msps,
                              {"source": 1.0, "sink": 1.0}) if with_pass else {}
    # The relay phase over the subscriber's receipts of the relayed power: every sample went through all three.
    relayed = sink.get("relayed") or {}
    relay_msps = relayed.get("msamples_per_s", 0.0)
    procs_relay = _per_process(cpu_samples, relayed.get("t_first_ns"), relayed.get("t_last_ns"), relay_msps,
                               {"source": 1.0, "relay": 1.0, "sink": 1.0}) if with_relay else {}
    relay_per_core = procs_relay.get("relay", {}).get("msamples_per_cpu_s")
    cores_stream = {k: v["cores"] for k, v in procs_stream.items()}
    cores_pass = {k: v["cores"] for k, v in procs_pass.items()}
    per_core = procs_stream.get("converter", {}).get("msamples_per_cpu_s")
    pass_per_core = procs_pass.get("sink", {}).get("msamples_per_cpu_s")
    rec_cpu = sum(procs_stream.get(name, {}).get("cpu_s", 0.0) for name in rec_names)
    stream_cpu_wall = _cpu_used(cpu_samples, src["t_start_ns"], stream_end)[0]
    rec_per_cpu = msps * stream_cpu_wall / rec_cpu if rec_cpu > 0 else None
    stream_wall = (src["t_end_ns"] - src["t_start_ns"]) / 1e9
    # A service that did not stop cleanly (exit code) or gave no result: named, so a failed trial says which.
    failed = [name for name in names if not stopped.get(name) or not isinstance(results.get(name), dict)]

    def cpu(r):
        return round(r.get("process_cpu_s", 0.0) / r.get("process_wall_s", 1.0), 3) if isinstance(r, dict) else None

    def ratio(a, b):
        return round(a / b, 3) if a and b else None

    # Per chunk, same run: the converter's CPU in the stream phase outside its kernel calls (their CPU it counts
    # itself) over the relay's CPU in its phase: what the converter's Python costs next to the transport's floor.
    conv_cpu = procs_stream.get("converter", {}).get("cpu_s")
    kernel_cpu = conv.get("kernel_cpu_s") if isinstance(conv, dict) else None
    n_conv = conv.get("chunks_converted") if isinstance(conv, dict) else None
    relay_cpu, n_relayed = procs_relay.get("relay", {}).get("cpu_s"), relayed.get("messages")
    conv_us = conv_cpu / n_conv * 1e6 if conv_cpu and n_conv else None
    kernel_us = kernel_cpu / n_conv * 1e6 if kernel_cpu is not None and n_conv else None
    relay_us = relay_cpu / n_relayed * 1e6 if relay_cpu and n_relayed else None
    outside_us = conv_us - kernel_us if conv_us is not None and kernel_us is not None else None

    out = {
        "channels": args.modules * args.channels,
        "modules": args.modules,
        "sample_rate_hz": args.sample_rate,
        "chunk_s": n / args.sample_rate,
        "mode": "flat-out" if args.flat_out else "real time",
        "duration_s": args.duration,
        "offered_msamples_per_s": round(args.modules * args.channels * args.sample_rate / 1e6, 4),
        "msamples_per_s": round(msps, 4),
        # Flat out, the data clock runs ahead of the wall clock: no latency to speak of.
        "latency_p50_ms": None if args.flat_out else round(q[49], 2),
        "latency_p99_ms": None if args.flat_out else round(q[98], 2),
        "latency_max_ms": None if args.flat_out or not lat else round(max(lat), 2),
        "chunks_sent": src["chunks_sent"],
        "chunks_converted": conv.get("chunks_converted") if isinstance(conv, dict) else None,
        "chunks_recorded": unique_power,
        "counts_recorded": counts_msgs,
        "power_duplicates_recorded": power_msgs - unique_power,
        "lost": src["chunks_sent"] - unique_power,
        # Set when the run ended on the converter's stall short of every chunk (seconds without progress):
        # the chunks it had not taken by then count as lost above, though a longer wait might have seen them.
        "stalled_s": stalled,
        "converter_lost": conv.get("chunks_lost") if isinstance(conv, dict) else None,
        # Overload (a real one: behind without a break for overload_after_s): set aside, converted late when
        # there was time, shed beyond the set-aside budget; in the converter's ledger either way.
        "converter_shed": conv.get("chunks_shed") if isinstance(conv, dict) else None,
        "converter_late": conv.get("chunks_late") if isinstance(conv, dict) else None,
        "converter_ledger": conv.get("ledger_line") if isinstance(conv, dict) else None,
        "source_behind_max_ms": round(src.get("behind_max_ms", 0.0), 2),
        "stream_wall_s": round(stream_wall, 2),
        "passthrough_msamples_per_s": round(pass_msps, 3) if with_pass else None,
        "ratio_to_passthrough": ratio(msps, pass_msps),
        # Per process and phase (from /proc, sampled about every 0.1 s): CPU seconds, cores, and M samples
        # per CPU second of what went through it; a process idle in a phase has no rate there.
        "per_process": {"stream": procs_stream, "passthrough": procs_pass, "relay": procs_relay},
        "cores_during_stream": cores_stream,
        "cores_during_passthrough": cores_pass,
        # Per core of the process itself: the converter's rate per core it used, the plain subscriber's likewise.
        "converter_msamples_per_core_s": per_core,
        "passthrough_msamples_per_core_s": pass_per_core,
        "ratio_per_core": ratio(per_core, pass_per_core),
        # The relay (a converter whose conversion costs nothing, see the module docstring): the ceiling of the
        # converter's rate per core on this transport, and the converter's share of it.
        "relay_msamples_per_s": round(relay_msps, 3) if with_relay else None,
        "relay_chunks": relay.get("messages") if with_relay and isinstance(relay, dict) else None,
        "relay_msamples_per_core_s": relay_per_core,
        "relay_ratio_per_core": ratio(relay_per_core, pass_per_core),
        "converter_ratio_to_relay": ratio(per_core, relay_per_core),
        # CPU microseconds per chunk: the converter's in the stream phase, of it inside its kernel calls (the
        # converter's own thread CPU around them), the relay's in its phase; and the converter's outside its
        # kernel over the relay's (issue 35: target <= 1.3).
        "converter_cpu_us_per_chunk": round(conv_us, 1) if conv_us else None,
        "converter_kernel_cpu_s": kernel_cpu,
        "converter_kernel_us_per_chunk": round(kernel_us, 1) if kernel_us is not None else None,
        # Chunks one kernel call took on average: the kernel's CPU per chunk falls as batches grow (a converter
        # keeping up converts a readout step at a time; one catching up, several), so it reads beside it.
        "converter_chunks_per_kernel_call": (round(conv["chunks_per_kernel_call"], 1)
                                             if isinstance(conv, dict) and conv.get("chunks_per_kernel_call") else None),
        "relay_cpu_us_per_chunk": round(relay_us, 1) if relay_us else None,
        "converter_overhead_per_relay": ratio(outside_us, relay_us),
        "recorder_msamples_per_cpu_s": round(rec_per_cpu, 3) if rec_per_cpu else None,
        "cpu_fraction": {"source": cpu(src), "converter": cpu(conv), **({"sink": cpu(sink)} if with_pass else {}),
                         **({"relay": cpu(relay)} if with_relay else {}),
                         **{name: cpu(results.get(name, {})) for name in rec_names}},
        "converter_threads": args.threads,
        "recorder_shards": args.recorder_shards,
        "compression": args.compression,
        # Each process's peak resident memory (its own getrusage, at its end), and how much it grew in each half
        # of the stream phase (sampled from /proc): a process still growing in the second half is not bounded.
        "max_rss_mb": {name: round(r["process_max_rss_mb"]) if isinstance(r, dict) and "process_max_rss_mb" in r
                       else None for name, r in ((name, results.get(name)) for name in names)},
        "rss_growth_mb": _rss_growth(rss_samples, src["t_start_ns"], stream_end) if stream_end else {},
        # The converter's receive queue at its fullest: within [converter] queue_mb whatever the rate.
        "converter_queue_high_water_mb": conv.get("queue_high_water_mb") if isinstance(conv, dict) else None,
        "recording_mb": round(sum(f.stat().st_size for f in rec_dir.glob("*.mcap")) / 1e6, 1),
        "kind": args.kind,
        # Other work on the machine shows in the latency tail: say how busy it was.
        "load_average_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        "all_services_ok": bool(not failed and ok_all),
        "failed_services": failed,
    }
    if tmp is not None:
        tmp.cleanup()
    return out
