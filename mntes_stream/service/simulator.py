"""The array simulator as a data source: live over zenoh or into an MCAP file, truth alongside.

Generator contract (shared with :mod:`mntes_stream.service.source`): an
iterable of batches ``(t_pub_ns, [(key, payload), ...])`` in publication
order, ``t_pub_ns`` being when the batch is due on the data clock. Each batch
closes one chunk: first the housekeeping read during it (``t_bath``,
``b_field``, and ``bias/<board>/<module>`` per module, each at its own cadence
and with its own timestamps), then one counts chunk per module. Housekeeping
readings are causal: a reading is published in the batch after it was taken,
so the converter may hold a chunk until the reading after its last sample
arrives.

The truth (optical power, environment and TES state at every sample) never
travels with the counts: :class:`TruthRecorder` keeps it for a separate
``.npz`` file whose arrays say they are truth.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mntes_stream import __version__
from mntes_stream.core.ids import NAME_PATTERN
from mntes_stream.core.params import DetectorParams
from mntes_stream.core.settings import Settings, setting
from mntes_stream.core.sim import ArraySimulator, SimBlock, SimConfig
from mntes_stream.errors import ConfigError
from mntes_stream.io import keys
from mntes_stream.io.messages import CountsChunk, HousekeepingChunk
from mntes_stream.io.transport import ZenohSettings
from mntes_stream.service.base import Service
from mntes_stream.service.metrics import MetricsSettings
from mntes_stream.service.source import Batch, PacedBatches

__all__ = ["SimulatorSource", "SimulatorService", "SimulatorServiceConfig", "TruthRecorder", "write_mcap",
           "run_simulator", "load_truth", "TRUTH_NOTE"]

log = logging.getLogger("mntes_stream.simulator")

TRUTH_NOTE = "TRUTH: simulator ground truth. Never an input to a converter."


class SimulatorSource:
    """Counts and housekeeping messages from an :class:`ArraySimulator`.

    Parameters
    ----------
    config : SimConfig
    setup : str
        Setup name in the zenoh keys.
    chunk_s : float
        Chunk length (rounded to whole samples, at least one).
    """

    def __init__(self, config: SimConfig, setup: str = keys.DEFAULT_SETUP, chunk_s: float = 0.1):
        keys.counts_key(setup)  # validates the name
        if not chunk_s > 0:
            raise ConfigError("simulator: chunk_s must be > 0")
        self.config = config
        self.setup = setup
        self.chunk_samples = max(1, int(round(chunk_s * config.sample_rate_hz)))
        self._sim = ArraySimulator(config)

    @property
    def params(self) -> list[DetectorParams]:
        """The truth parameters (write them with ``io.paramfile.dump_params``)."""
        return list(self._sim.truth_params)

    @property
    def detector_ids(self) -> tuple:
        return self._sim.detector_ids

    def wait_keys(self) -> list[str]:
        c = self.config
        return [keys.counts_key(self.setup, b, m) for b in range(c.boards) for m in range(c.modules)]

    def n_chunks(self, duration_s: float) -> int | None:
        """Chunks covering ``duration_s`` of data (None: forever)."""
        if not duration_s:
            return None
        return max(1, math.ceil(duration_s * self.config.sample_rate_hz / self.chunk_samples))

    def batches(self, t_start_ns: int, duration_s: float = 0.0, truth: TruthRecorder | None = None,
                blocks: list | None = None) -> Iterator[Batch]:
        """Batches from ``t_start_ns`` on, ``duration_s`` of data (0: forever).

        ``truth`` receives every simulated block; ``blocks``, if a list, too
        (tests compare messages with the blocks they came from).
        """
        c = self.config
        sim = ArraySimulator(c, t0_ns=int(t_start_ns))
        channels = np.arange(c.channels, dtype=np.int32)
        hk_seq: dict[str, int] = {}
        n_total = self.n_chunks(duration_s)
        step = 0
        while n_total is None or step < n_total:
            blk = sim.next_block(self.chunk_samples)
            t_pub_ns = sim.sample_time_ns(sim.position)  # end of the chunk: all of it has been sampled
            if truth is not None:
                truth.add(blk)
            if blocks is not None:
                blocks.append(blk)
            batch: list[tuple[str, bytes]] = []
            for h in blk.hk:
                sensor_key = keys.hk_sensor(h.sensor, h.board, h.module)
                seq = hk_seq.get(sensor_key, 0)
                hk_seq[sensor_key] = seq + 1
                msg = HousekeepingChunk(setup=self.setup, sensor=h.sensor, seq=seq, t_ns=h.t_ns, value=h.value,
                                        unit=h.unit, board=h.board, module=h.module, channels=h.channels)
                batch.append((keys.hk_key(self.setup, sensor_key), msg.to_bytes()))
            for b in range(c.boards):
                for m in range(c.modules):
                    rows = sim.module_rows(b, m)
                    chunk = CountsChunk(
                        setup=self.setup, board=b, module=m, channels=channels, seq=step,
                        t0_ns=int(blk.t_ns[0]), sample_rate_hz=c.sample_rate_hz,
                        counts_i=blk.counts_i[rows], counts_q=blk.counts_q[rows], t_pub_ns=t_pub_ns,
                    )
                    batch.append((keys.counts_key(self.setup, b, m), chunk.to_bytes()))
            yield t_pub_ns, batch
            step += 1


class TruthRecorder:
    """Collects the truth of every block for one ``.npz`` file.

    Parameters
    ----------
    detector_ids : sequence of str
    config : SimConfig
    max_bytes : int
        Refuse to grow beyond this (the truth is held in memory until saved).
    """

    def __init__(self, detector_ids, config: SimConfig, max_bytes: int = 2 << 30):
        self.detector_ids = tuple(detector_ids)
        self.config = config
        self.max_bytes = int(max_bytes)
        self._blocks: list[SimBlock] = []
        self._bytes = 0

    def add(self, blk: SimBlock) -> None:
        # p_opt, v (float64) and state (int8) per detector and sample.
        self._bytes += blk.truth_p_opt_w.size * 17 + blk.n_samples * 24
        if self._bytes > self.max_bytes:
            raise ConfigError(
                f"truth would exceed {self.max_bytes / 2**30:.1f} GiB in memory: shorten the run, "
                "simulate fewer channels, or drop --truth"
            )
        self._blocks.append(blk)

    def save(self, path: str | Path) -> Path:
        """Write the truth (``p_opt_w`` etc., all marked truth) as a compressed ``.npz``."""
        path = Path(path)
        if not self._blocks:
            raise ConfigError("no truth to save: nothing was simulated")
        cat = lambda name, axis: np.concatenate([getattr(b, name) for b in self._blocks], axis=axis)  # noqa: E731
        np.savez_compressed(
            path,
            note=np.array(TRUTH_NOTE),
            detector_ids=np.array(self.detector_ids),
            t_ns=cat("t_ns", 0),
            truth_p_opt_w=cat("truth_p_opt_w", 1),
            truth_t_bath_k=cat("truth_t_bath_k", 0),
            truth_b_field_t=cat("truth_b_field_t", 0),
            truth_v_thev_v=cat("truth_v_thev_v", 1),
            truth_state=cat("truth_state", 1),
            sim_config_json=np.array(json.dumps(self.config.to_dict())),
        )
        return path


def load_truth(path: str | Path) -> dict:
    """Read a truth file written by :class:`TruthRecorder` (arrays by name)."""
    import zipfile

    try:
        z = np.load(path, allow_pickle=False)
    except (ValueError, EOFError, zipfile.BadZipFile) as exc:  # a text file, a truncated archive
        raise ConfigError(f"{path}: not a simulator truth file ({type(exc).__name__})") from None
    if not isinstance(z, np.lib.npyio.NpzFile):  # a .npy: one array
        raise ConfigError(f"{path}: not a simulator truth file (one array, not an .npz)")
    with z:
        out = {k: z[k] for k in z.files}
    if str(out.get("note")) != TRUTH_NOTE:
        raise ConfigError(f"{path}: not a simulator truth file")
    out["sim_config"] = json.loads(str(out.pop("sim_config_json")))
    return out


def _metadata(source: SimulatorSource) -> dict[str, dict[str, str]]:
    from mntes_stream.io.mcap import writer_description
    from mntes_stream.io.paramfile import params_to_toml

    return {
        "mntes.recording": writer_description(writer="mntes-stream simulate"),
        "mntes.simulation": {
            "software": f"mntes-stream {__version__}",
            "setup": source.setup,
            "chunk_samples": str(source.chunk_samples),
            "sim_config": json.dumps(source.config.to_dict()),
            "truth_params_toml": params_to_toml(source.params, {"source": "mntes-stream simulate (truth)"}),
        },
    }


def write_mcap(source: SimulatorSource, path: str | Path, duration_s: float, t_start_ns: int | None = None,
               truth: TruthRecorder | None = None, progress=None) -> dict:
    """Simulate ``duration_s`` of data into one MCAP file (log time = publication time on the data clock).

    Returns
    -------
    dict
        ``path``, ``chunks``, ``messages``, ``bytes``, ``samples``, ``elapsed_s``.
    """
    from mntes_stream.io.mcap import McapFileWriter

    if not duration_s > 0:
        raise ConfigError("simulate --out FILE.mcap needs a duration > 0")
    t_start = time.time_ns() if t_start_ns is None else int(t_start_ns)
    wall = time.perf_counter()
    n = 0
    with McapFileWriter(path, metadata=_metadata(source)) as writer:
        for t_pub_ns, batch in source.batches(t_start, duration_s, truth=truth):
            for key, payload in batch:
                writer.write(key, payload, t_pub_ns)
            n += 1
            if progress is not None:
                progress(1)
        messages, nbytes = writer.messages, writer.payload_bytes
    return {"path": str(path), "chunks": n, "messages": messages, "bytes": nbytes,
            "samples": n * source.chunk_samples * source.config.n_detectors,
            "elapsed_s": time.perf_counter() - wall}


def perturbed_params(params: list[DetectorParams], scale: float = 1.0, seed: int = 0) -> list[DetectorParams]:
    """The truth with random calibration errors: each of ``core.validation.CALIBRATION_ERRORS``
    drawn per detector from N(0, scale x its assumed 1-sigma level)."""
    from mntes_stream.core.validation import CALIBRATION_ERRORS, perturb_params

    rng = np.random.default_rng([int(seed), 11])
    out = []
    for p in params:
        errors = {name: scale * sigma * rng.standard_normal() for name, (_, sigma, _, _) in CALIBRATION_ERRORS.items()}
        out.append(perturb_params(p, errors))
    return out


@dataclass(frozen=True)
class SimulatorServiceConfig(Settings):
    """The ``[simulator]`` (+ ``[zenoh]``) tables: any :class:`SimConfig` field, plus how to run it."""

    sim: SimConfig = setting(default_factory=SimConfig, doc="the simulated array (core.sim.SimConfig)", flatten=True)
    setup: str = setting(keys.DEFAULT_SETUP, "keys mntes/<setup>/...", pattern=NAME_PATTERN)
    chunk_s: float = setting(0.1, "one counts chunk per module this often (whole samples)", unit="s", gt=0)
    speed: float = setting(1.0, "multiple of real time (0 = as fast as possible)", ge=0)
    duration_s: float = setting(0.0, "seconds of data (0 = until stopped)", unit="s", ge=0)
    linger_s: float = setting(1.0, "keep the session open this long after the last batch (queued is not delivered)",
                              unit="s", ge=0)
    params_out: str = setting("", "write the truth parameters (the converter's calibration) here at start", path=True)
    metrics: MetricsSettings = setting(default_factory=MetricsSettings, doc="Prometheus endpoint ([metrics])")
    zenoh: ZenohSettings = setting(default_factory=ZenohSettings, doc="how to join zenoh ([zenoh])")


def run_simulator(cfg: SimulatorServiceConfig, stop=None, ready=None, truth: TruthRecorder | None = None,
                  source: SimulatorSource | None = None) -> dict:
    """Publish until ``duration_s`` of data is out or ``stop`` is set (SIGINT/SIGTERM set it too).

    ``ready`` is set once the truth parameters are written (``params_out``) and the session is open;
    the clock starts when the converter has subscribed (or after 10 s). ``source``: the
    ``SimulatorSource`` of ``cfg`` when the caller built it already (seconds for a large array).
    """
    service = SimulatorService(cfg)
    service.truth, service.source = truth, source
    return dict(service.run(stop, ready))


class SimulatorService(PacedBatches, Service):
    """The array simulator live over zenoh (MNTES physics, housekeeping, truth kept apart)."""

    name = "simulator"
    Config = SimulatorServiceConfig
    summary = "the simulated DfMux array, live"
    #: seconds to wait for a subscriber to the counts before the data clock starts
    WAIT_S = 10.0
    truth: TruthRecorder | None = None
    #: the SimulatorSource of the config, when built already (None: setup builds it)
    source: SimulatorSource | None = None

    def duration_s(self) -> float:
        return 0.0  # duration_s is seconds of data: the batches end there

    def history_chunks(self) -> int:
        from mntes_stream.io.history import cache_chunks

        return cache_chunks(self.config.zenoh.history_seconds, self.config.chunk_s)

    def setup(self, ctx) -> None:
        from mntes_stream.service.source import Pacer

        cfg = self.config
        source = self.source if self.source is not None else SimulatorSource(cfg.sim, cfg.setup, cfg.chunk_s)
        if cfg.params_out:
            from mntes_stream.io.paramfile import dump_params

            dump_params(source.params, cfg.params_out, metadata={"source": "mntes-stream simulator (truth)",
                                                                 "sim_config": json.dumps(cfg.sim.to_dict())})
        ctx.mark_ready()
        # Wait for the converter before the data clock starts, so waiting is not latency.
        self._matched = ctx.publishers.wait_matching(source.wait_keys(), self.WAIT_S, ctx.stop)
        if not self._matched:
            log.warning("simulator: no subscriber for the counts yet; publishing anyway")
        start = time.time_ns()
        self._batches = source.batches(start, cfg.duration_s, truth=self.truth)
        self._pacer = Pacer(cfg.speed, start)
        self._n_batches = 0
