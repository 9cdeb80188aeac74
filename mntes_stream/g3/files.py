"""``convert`` and ``export`` on G3 files: either layout in, G3 or MCAP out, and recordings out to G3.

- G3 -> G3: :class:`~mntes_stream.g3.power.OpticalPower` in a ``G3Pipeline``
  (raw Timepoint files go through spt3g's ``FixedLengthScans`` and
  ``DfMuxCollator`` first); the housekeeping of the whole run is read ahead.
- G3 -> MCAP: the frames become counts and housekeeping messages
  (:class:`~mntes_stream.g3.translate.FrameTranslator`, as the live bridge
  publishes them), and the recording is converted by the live converter's own
  pipeline (``pipeline.offline.convert_recording``) with the parameters mapped
  to detector ids and the gain of the first housekeeping.
- MCAP -> G3: the recorded (or, with parameters or tables, re-converted)
  power as Scan frames with ``MntesOpticalPower``/``MntesFlags``, keyed by
  bolometer name when a wiring map is given (a G3 file holding one).

Every G3 file is read through :mod:`~mntes_stream.g3.wire` (length claims
bounded, a frame spt3g cannot decode counted and skipped, a cut-off tail
counted) and every G3 file written appears under its name only when
complete (``OUT.g3.partial`` until then; a full disk is a one-line error
and leaves nothing). Frames skipped on the way are counted by reason in the
result (``rejected_frames``), said on the log, and marked in the output: a
``PipelineInfo`` frame with ``MntesRejectedFrames`` (reason -> count)
before the end.
"""

from __future__ import annotations

import dataclasses
import glob
import logging
import tempfile
from pathlib import Path

import numpy as np

from mntes_stream.errors import ConfigError
from mntes_stream.g3.mapping import Wiring
from mntes_stream.g3.runtime import spt3g
from mntes_stream.g3.settings import G3InputConfig
from mntes_stream.g3.wire import AtomicG3Writer

MAX_FRAME_BYTES = 512 << 20  # a frame of a G3 file claiming more is not read (the bridge's max_frame_mb)

__all__ = ["is_g3", "expand_inputs", "read_frames", "preload", "g3_to_g3", "g3_to_mcap", "mcap_to_g3",
           "g3_messages", "converter_params", "write_converter_params"]

log = logging.getLogger("mntes_stream.g3")


def is_g3(path) -> bool:
    """A G3 file by its name (``.g3``, ``.g3.gz``, ``.g3.zst``, ``.g3.bz2``)."""
    name = str(path).lower()
    return any(name.endswith(s) for s in (".g3", ".g3.gz", ".g3.zst", ".g3.bz2"))


def expand_inputs(paths) -> list[str]:
    """Files named by paths or glob patterns, in order (ConfigError if a pattern matches nothing)."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    out: list[str] = []
    for p in paths:
        p = str(p)
        if any(ch in p for ch in "*?["):
            hits = sorted(glob.glob(p))
            if not hits:
                raise ConfigError(f"no G3 file matches {p!r}")
            out += hits
        elif not Path(p).is_file():
            raise ConfigError(f"G3 file not found: {p}")
        else:
            out.append(p)
    return out


def read_frames(paths, bad: dict | None = None, max_frame_bytes: int = MAX_FRAME_BYTES):
    """Every frame of the files, in order; frames that cannot be read are counted in ``bad`` (reason -> n).

    A file that is not G3 at all is a ConfigError.
    """
    from mntes_stream.g3.wire import iter_file_frames

    for path in expand_inputs(paths):
        yield from iter_file_frames(path, max_frame_bytes, bad)


def _report(bad: dict, what) -> None:
    if any(bad.values()):
        log.warning("%s: %d G3 frame(s) skipped (%s)", what, sum(bad.values()),
                    ", ".join(f"{r} {n}" for r, n in sorted(bad.items())))


def _merge(*counts: dict) -> dict:
    out: dict = {}
    for c in counts:
        for r, n in c.items():
            out[r] = out.get(r, 0) + n
    return out


def _rejected_frame(bad: dict):
    """The output's mark of what is missing from it: PipelineInfo with MntesRejectedFrames (reason -> count)."""
    core, _ = spt3g()
    f = core.G3Frame(core.G3FrameType.PipelineInfo)
    f["MntesRejectedFrames"] = core.G3MapInt({str(r): int(n) for r, n in bad.items()})
    return f


def preload(paths) -> tuple[list, dict]:
    """Wiring, Housekeeping and GcpSlow frames of a run, and how many frames of each type it has."""
    core, _ = spt3g()
    from mntes_stream.g3.translate import check_frame
    from mntes_stream.g3.wire import BadFrame

    keep = (core.G3FrameType.Wiring, core.G3FrameType.Housekeeping, core.G3FrameType.GcpSlow)
    frames, counts, bad = [], {}, {}
    for f in read_frames(paths, bad):  # what is bad is counted again by the pass that converts
        counts[str(f.type)] = counts.get(str(f.type), 0) + 1
        if f.type in keep:
            try:
                check_frame(f)
            except (BadFrame, RuntimeError):
                continue
            frames.append(f)
        elif f.type == core.G3FrameType.Scan and "RawTimestreams_I" in f:
            counts["ScanData"] = counts.get("ScanData", 0) + 1
    files = expand_inputs(paths)
    where = f"{files[0]}{f' (+{len(files) - 1} files)' if len(files) > 1 else ''}: "
    damaged = f" (frames unreadable: {', '.join(f'{r} {n}' for r, n in sorted(bad.items()))})" if bad else ""
    if not counts.get("Wiring"):
        raise ConfigError(f"{where}the G3 input has no Wiring frame (WiringMap): cannot tell which bolometer is "
                          f"which{damaged}")
    if not counts.get("ScanData") and not counts.get("Timepoint"):
        raise ConfigError(f"{where}the G3 input has neither Timepoint frames nor Scan frames with "
                          f"RawTimestreams_I/Q{damaged}")
    return frames, counts


def g3_to_g3(inputs, output, *, params=None, kind: str = "table", config: G3InputConfig | None = None,
             scan_samples: int = 1000, pipeline_config=None, **converter_options) -> dict:
    """MNTES power appended to every Scan frame of a G3 run, written to ``output`` (G3).

    With parameters the power comes from the converter pipeline's stages (``pipeline_config``), as
    :func:`g3_to_mcap`'s does: the same values and flags.
    """
    from mntes_stream.g3.power import OpticalPower

    core, dfmux = spt3g()
    if Path(output).exists():
        raise ConfigError(f"{output} exists: not overwritten")
    files = expand_inputs(inputs)
    metadata, counts = preload(files)
    module = OpticalPower(params=params, kind=kind, config=config, preload=metadata, pipeline_config=pipeline_config,
                          **converter_options)
    if module.needs_bath:
        module.bath.require()
    bad: dict = {}
    frames = read_frames(files, bad)

    def source(_frame):
        if writer.error is None:  # a failed write ends the run
            for f in frames:
                return [f]
        return []

    with AtomicG3Writer(output, defer_errors=True) as writer:
        pipe = core.G3Pipeline()
        pipe.Add(source)
        if counts.get("Timepoint"):
            pipe.Add(_screen(bad))  # the collator must not meet a malformed Timepoint
            if not counts.get("Scan"):
                pipe.Add(dfmux.FixedLengthScans, N=int(scan_samples))
            pipe.Add(dfmux.DfMuxCollator, flac_compress=True)
        pipe.Add(module)
        pipe.Add(writer)
        try:
            pipe.Run()
        except RuntimeError as exc:
            raise ConfigError(f"{files[0]}: G3 conversion failed ({str(exc).split(' (in ', 1)[0]}); nothing "
                              "written") from None
        rejected = _merge(bad, module.rejected)
        if rejected:
            writer(_rejected_frame(rejected))
    _report(rejected, f"convert {files[0]} -> {output}")
    return {"output": str(output), "layout": "timepoints" if counts.get("Timepoint") else "scans",
            "scans": module.scans, "detector_samples": module.samples, "skipped_bolometers": len(module.skipped),
            "housekeeping_changes": module.gain_changes, "kind": kind, "rejected_frames": rejected}


def _screen(bad: dict):
    """A pipeline module dropping (and counting) frames whose DfMux entries have the wrong class or none."""
    from mntes_stream.g3.translate import check_frame
    from mntes_stream.g3.wire import BadFrame

    def screen(frame):
        try:
            check_frame(frame)
        except BadFrame as exc:
            bad[exc.reason] = bad.get(exc.reason, 0) + 1
            return []
        except RuntimeError:
            bad["undecodable"] = bad.get("undecodable", 0) + 1
            return []
        return None

    return screen


def g3_messages(inputs, setup: str, config: G3InputConfig | None = None, chunk_samples: int = 16,
                gain_reference=None, bad: dict | None = None, hk=None):
    """``(t_ns, key, payload)`` of every message a G3 run gives (the bridge's translation).

    ``t_ns`` is the data time the message stands for (last sample of a
    chunk, time of a reading); bath readings of a configured default come
    with every counts batch when the run has no thermometer. ``hk``:
    housekeeping messages from elsewhere (OCS HK files, ``--hk``) in time
    order, merged by time; the run's own readings of their sensors are left out.
    """
    if hk:
        from mntes_stream.g3.ocs_hk import merge_by_time

        hk = list(hk)
        replaced = {key for _, key, _ in hk}
        has_t_bath = any(key.endswith("/hk/t_bath") for key in replaced)
        # With the bath from elsewhere the run needs no thermometer: a placeholder default, whose
        # readings are left out with the run's own.
        own = g3_messages(inputs, setup, config if not has_t_bath else
                          dataclasses.replace(config or G3InputConfig(), t_bath_default_k=1.0),
                          chunk_samples, gain_reference, bad)
        yield from merge_by_time((m for m in own if m[1] not in replaced), hk)
        return
    from mntes_stream.g3.mapping import bath_reading
    from mntes_stream.g3.translate import FrameTranslator
    from mntes_stream.io import keys

    core, _ = spt3g()
    config = config or G3InputConfig()
    metadata, _ = preload(inputs)
    has_bath = any(bath_reading(f, config, 0) is not None for f in metadata if f.type == core.G3FrameType.GcpSlow)
    if not has_bath and config.t_bath_default_k is None:
        from mntes_stream.g3.mapping import BathHistory

        BathHistory(config).require()  # the one-line error naming the setting
    tr = FrameTranslator(setup, config, chunk_samples, gain_reference=gain_reference)
    t_default = None

    def with_default(items):
        nonlocal t_default
        for t_ns, key, payload in items:
            if not has_bath and keys.kind_of(key) == "counts" and t_ns != t_default:
                t_default = t_ns  # one default reading per chunk time, before the chunks it covers
                yield from tr.timed(tr.default_bath, t_ns)
            yield t_ns, key, payload

    read_bad: dict = {}
    for frame in read_frames(inputs, read_bad):
        yield from with_default(tr.timed(tr.accept, frame))
    yield from with_default(tr.timed(tr.flush))
    tr.drop_held()
    if bad is not None:
        bad.update(_merge(read_bad, tr.counters.rejected))


def converter_params(inputs, params, config: G3InputConfig | None = None) -> dict:
    """The converter's parameters for a G3 run: keyed by detector id, gain of the first housekeeping.

    Parameters
    ----------
    inputs : path(s) of the run (its Wiring and first Housekeeping frame are used)
    params : path or mapping, keyed by bolometer name or detector id
    """
    from mntes_stream.g3.mapping import hk_snapshot, params_for_wiring
    from mntes_stream.g3.power import load_g3_params

    core, _ = spt3g()
    wiring, hk = None, None
    for f in read_frames(inputs):
        if f.type == core.G3FrameType.Wiring and wiring is None:
            wiring = Wiring.from_frame(f, config)
        elif f.type == core.G3FrameType.Housekeeping and "DfMuxHousekeeping" in f and hk is None:
            hk = f["DfMuxHousekeeping"]
        if wiring is not None and hk is not None:
            break
    if wiring is None or hk is None:
        raise ConfigError("the G3 input needs a Wiring frame and DfMux housekeeping (amps per count, bias)")
    pdict, missing = params_for_wiring(load_g3_params(params), wiring, hk_snapshot(hk, wiring))
    if missing:
        log.warning("%d wired bolometer(s) without parameters, skipped: %s%s", len(missing), ", ".join(missing[:8]),
                    " ..." if len(missing) > 8 else "")
    if not pdict:
        raise ConfigError("no wired bolometer has parameters: keyed by bolometer name or detector id?")
    return pdict


def write_converter_params(inputs, params, output, config: G3InputConfig | None = None) -> int:
    """Write the converter's parameter file for a G3 run (``mntes-stream params``); the number of detectors.

    The file is keyed by detector id, with each detector's gain from the run's
    first housekeeping: what the live converter, ``g3-bridge --params`` and
    ``convert RUN.g3`` all take as it is.
    """
    from mntes_stream.io.paramfile import dump_params

    files = expand_inputs(inputs)
    pdict = converter_params(files, params, config)
    dump_params(list(pdict.values()), output,
                metadata={"source": f"mntes-stream params: {params} for the G3 run {files[0]} (keyed by detector id, "
                                    "gain from its first housekeeping)"})
    return len(pdict)


def g3_to_mcap(inputs, output, *, params, config: G3InputConfig | None = None, setup: str = "lab",
               chunk_samples: int = 16, tables=None, pipeline_config=None, progress: bool = False, hk=None):
    """Convert a G3 run to an MCAP recording through the live converter's pipeline.

    ``hk``: housekeeping messages replacing the run's own (OCS HK files, see :func:`g3_messages`).
    """
    from mntes_stream.io.mcap import McapFileWriter, writer_description
    from mntes_stream.io.paramfile import dump_params
    from mntes_stream.pipeline.offline import convert_recording

    if params is None and tables is None:
        raise ConfigError("G3 -> MCAP needs detector parameters (--params, keyed by bolometer name or detector id)")
    if Path(output).exists():
        raise ConfigError(f"{output} exists: not overwritten")
    config = config or G3InputConfig()
    files = expand_inputs(inputs)
    with tempfile.TemporaryDirectory(prefix="mntes-g3-") as tmp:
        pfile, gref = None, None
        if params is not None:
            pfile = Path(tmp) / "params.toml"
            pdict = converter_params(files, params, config)
            dump_params(list(pdict.values()), pfile, metadata={"source": f"G3 run {files[0]}: gain from housekeeping"})
            gref = {d: abs(p.gain_a_per_count) for d, p in pdict.items()}  # later gain changes rescale the counts
        rec = Path(tmp) / "g3.mcap"
        with McapFileWriter(rec, metadata={"mntes.recording": writer_description(
                mode="G3 translation", input=[str(f) for f in files])}) as w:
            bad: dict = {}
            for t_ns, key, payload in g3_messages(files, setup, config, chunk_samples, gain_reference=gref, bad=bad,
                                                  hk=hk):
                w.write(key, payload, t_ns)
        _report(bad, f"convert {files[0]} -> {output}")  # their samples are missing from the output
        return convert_recording(rec, output, params=pfile, tables=tables, pipeline_config=pipeline_config,
                                 progress=progress)


def mcap_to_g3(inputs, output, *, params=None, tables=None, wiring=None, pipeline_config=None) -> dict:
    """Recorded power (re-converted when ``params``/``tables`` are given) as G3 Scan frames."""
    from mntes_stream.io.mcap import Session
    from mntes_stream.io.messages import PowerChunk
    from mntes_stream.pipeline.offline import convert_recording

    core, _ = spt3g()
    if Path(output).exists():
        raise ConfigError(f"{output} exists: not overwritten")
    wiring_frame = None
    names = {}
    if wiring is not None:
        wiring_frame = next((f for f in read_frames(wiring) if f.type == core.G3FrameType.Wiring), None)
        if wiring_frame is None:
            raise ConfigError(f"{wiring}: no Wiring frame")
        w = Wiring.from_frame(wiring_frame)
        names = dict(zip(w.detector_ids, w.names))
    with tempfile.TemporaryDirectory(prefix="mntes-g3-") as tmp:
        source = inputs
        if params is not None or tables is not None:
            source = Path(tmp) / "converted.mcap"
            convert_recording(inputs, source, params=params, tables=tables, pipeline_config=pipeline_config,
                              progress=False)
        groups: dict = {}
        for msg in Session(source).iter_messages():
            if not msg.topic.split("/")[2:3] == ["power"]:
                continue
            chunk = PowerChunk.from_bytes(msg.payload)
            t = chunk.times_ns()
            groups.setdefault((int(t[0]), t.size), []).append(chunk)
    with AtomicG3Writer(output) as writer:
        if wiring_frame is not None:
            writer(wiring_frame)
        n_scans = n_samples = 0
        for (_, _), chunks in sorted(groups.items()):
            t = chunks[0].times_ns()
            ids = [d for c in chunks for d in c.detector_ids]
            p = np.concatenate([c.p_opt_w for c in chunks])
            f = np.concatenate([c.flags for c in chunks]).astype(np.int32)
            keys_ = [names.get(d, d) for d in ids]
            start, stop = core.G3Time(int(t[0]) // 10), core.G3Time(int(t[-1]) // 10)
            frame = core.G3Frame(core.G3FrameType.Scan)
            frame["MntesOpticalPower"] = core.G3TimestreamMap(keys_, p, start, stop, core.G3TimestreamUnits.Power)
            frame["MntesFlags"] = core.G3TimestreamMap(keys_, f, start, stop)
            frame["DetectorSampleTimes"] = core.G3VectorTime([core.G3Time(int(x) // 10) for x in t])
            writer(frame)
            n_scans += 1
            n_samples += p.size
    return {"output": str(output), "scans": n_scans, "detector_samples": n_samples,
            "named_by": "bolometer name" if names else "detector id"}
