"""Offline re-conversion of a recording through the live converter's own pipeline.

The recorded counts and housekeeping are fed to
:class:`~mntes_stream.pipeline.pipeline.ConverterPipeline` in log-time order
with their recorded receive times, exactly as the live service feeds what its
subscriber receives; the inputs and everything the pipeline emits (power,
status, its provenance) are written to the output file. By default the
messages of each second of receive time go through the pipeline together
(``batch_s``), as a live converter takes its backlog: every chunk is held,
released and aligned message by message as before, and the chunks released
in a batch are converted together, in long kernel rows; the power and flags
are those of message-by-message conversion, bit for bit. Outputs are stamped
with the receive time of the last message of their batch (``clock=None``;
``batch_s=0``: of the message that produced them), so running the conversion
twice gives identical files' contents.

Parameters and tables default to the recording's own provenance
(``mntes.provenance`` attachments): detector parameters from its TOML text, the
converter kind from it, and for table kinds a table bank rebuilt from those
parameters whose identity must match the recorded one. When the calibration
changed during the recording (a converter restarted with other parameters or
tables), each part is converted with the calibration in force when it was
received: at the recorded receive time of a new provenance, what the old
pipeline holds is converted and a fresh pipeline with the new converter takes
over, as the restarted live converter did. ``tables`` (a table file) and
``params`` (a parameter TOML) override them for the whole recording, e.g. with
a newer calibration (with a warning if the recording held several).
"""

from __future__ import annotations

import logging
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from mntes_stream.core.ledger import Ledger
from mntes_stream.errors import ConfigError

__all__ = ["OfflineStats", "convert_recording", "converter_for", "recorded_calibrations", "spec_for"]

log = logging.getLogger("mntes_stream.offline")

# The output's chunks: lz4 in 256 KiB, the recorder's default by measurement (docs/recording.md). Writing the
# counts of 2,048 detectors x 30 s took 0.11 CPU s against 0.47 with zstd in 4 MiB chunks; the converted
# output (counts and power) is 17 % larger (159 MB against 136).
_COMPRESSION = "lz4"
_CHUNK_BYTES = 256 << 10
# A batch also ends at this much input payload, so a large focal plane's batch stays bounded in memory.
_BATCH_BYTES = 64 << 20


@dataclass(frozen=True)
class OfflineStats:
    """What an offline conversion did (``bad_messages`` by reason, as in the live status)."""

    input_messages: int
    power_chunks: int
    status_messages: int
    samples_converted: int
    bad_messages: dict
    chunks_lost: int
    converter_kind: str
    table_identity: str
    recorded_table_identity: str
    params_source: str
    tables_source: str
    output: str
    duration_s: float
    input_complete: bool
    flag_counts: dict = field(default_factory=dict)
    calibrations: int = 1  # recorded calibrations used (more than one: switched at their receive times)
    damaged: str = ""  # what of the input could not be read (chunks, messages, spans); "" when nothing
    damaged_messages: int = 0
    ledger: dict = field(default_factory=dict)  # core.ledger: every recorded counts chunk of every stream
    ledger_line: str = ""

    def summary(self) -> str:
        same = "same tables as recorded" if self.table_identity == self.recorded_table_identity else \
            f"recorded tables were {self.recorded_table_identity[:16] or 'unknown'}"
        bad = ", ".join(f"{k}={v}" for k, v in self.bad_messages.items() if v) or "none"
        return (f"converted {self.samples_converted / 1e6:.3f} Msamples in {self.power_chunks} power chunks from "
                f"{self.input_messages} recorded inputs in {self.duration_s:.1f} s -> {self.output}\n"
                f"  converter {self.converter_kind}, tables {self.table_identity[:16]} ({same})\n"
                f"  params: {self.params_source}; tables: {self.tables_source}; bad messages: {bad}"
                + (f"\n  the calibration changed {self.calibrations - 1} time(s) during the recording: each part "
                   "converted with its own (figures above: the last)" if self.calibrations > 1 else "")
                + ("" if self.input_complete else "\n  input was not finished by its recorder: converted what was recovered")
                + (f"\n  ledger: {self.ledger_line}" if self.ledger_line else "")
                # On the final line: what could not be read, and where the output marks it.
                + (f"{';' if self.ledger_line else chr(10) + ' '} input DAMAGED: {self.damaged} (converted what "
                   "was readable; the gap is in the output's mntes.damaged metadata)" if self.damaged else ""))


def _calibration(prov) -> tuple:
    """What decides a conversion (a restarted converter republishes it with a new ``t_ns``)."""
    return (prov.setup, prov.params_toml, prov.table_identity, prov.converter_kind)


def _owner(prov) -> str:
    """Which part of the focal plane a provenance speaks for ("" for the whole: an unsharded converter)."""
    import json

    return json.dumps(prov.owns, sort_keys=True) if prov.owns else ""


def _merged(parts: dict) -> object:
    """One provenance for the converter shards that together converted a setup: their parameters joined.

    A single part is itself. The joined parameters' tables are rebuilt (no one recorded bank has them
    all): ``table_identity`` is left empty, so :func:`converter_for` does not compare it.
    """
    import dataclasses

    from mntes_stream.io.paramfile import params_to_toml, parse_params

    if len(parts) == 1:
        return next(iter(parts.values()))
    provs = [parts[k] for k in sorted(parts)]
    kinds = {p.converter_kind for p in provs}
    if len(kinds) != 1:
        raise ConfigError(f"the recording's converter shards used different kinds {sorted(kinds)}: convert each "
                          "shard's streams with --params/--tables of its own")
    params: dict = {}
    for p in provs:
        try:
            params.update(parse_params(tomllib.loads(p.params_toml), "recorded provenance") if p.params_toml else {})
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"recorded provenance: parameter TOML unreadable: {exc}") from None
    return dataclasses.replace(provs[-1], params_toml=params_to_toml(list(params.values())), table_identity="",
                               owns={"shards": len(provs)})


def recorded_calibrations(session) -> list:
    """The calibrations a recording holds, in receive-time order.

    Parameters
    ----------
    session : mcap.Session

    Returns
    -------
    list of (int, Provenance)
        The recorded receive time (ns) of each provenance that changed the
        calibration of its setup, and that provenance. Rotated files repeat
        the latest provenance with its original receive time: counted once.
        Converter shards (provenances that say what they own) together make
        one calibration, their parameters joined: a shard first heard of joins
        the current one; a shard whose own calibration changes starts a new one.
    """
    from mntes_stream.errors import SchemaError
    from mntes_stream.io.mcap import PROVENANCE_ATTACHMENT
    from mntes_stream.io.messages import Provenance

    first: dict[tuple[int, bytes], int] = {}
    for k, a in enumerate(session.attachments()):
        if a.name == PROVENANCE_ATTACHMENT:
            first.setdefault((a.log_time_ns, a.data), k)
    epochs: list[tuple[int, str, dict]] = []  # (first receive time, setup, {owner: provenance})
    current: dict[str, int] = {}  # setup -> index in epochs
    for (t_ns, data), _ in sorted(first.items(), key=lambda kv: (kv[0][0], kv[1])):
        try:
            prov = Provenance.from_bytes(data)
        except SchemaError as exc:  # files of recorders that stored it unchecked
            log.warning("recorded provenance at log time %d unreadable, ignored: %s", t_ns, exc)
            continue
        owner = _owner(prov)
        k = current.get(prov.setup)
        parts = epochs[k][2] if k is not None else None
        if parts is not None and owner not in parts and "" not in parts and owner:
            parts[owner] = prov  # one more shard of the same calibration
        elif parts is None or owner not in parts or _calibration(parts[owner]) != _calibration(prov):
            new = {} if parts is None or not owner or "" in parts else {o: p for o, p in parts.items()}
            new[owner] = prov
            current[prov.setup] = len(epochs)
            epochs.append((t_ns, prov.setup, new))
    return [(t_ns, _merged(parts)) for t_ns, _, parts in epochs]


def _cache_dir(table_cache) -> str:
    """The table cache to use: ``...`` is the converter service's default, None or "" none."""
    if table_cache is ...:
        from mntes_stream.pipeline.build import default_table_cache

        return default_table_cache()
    return str(table_cache) if table_cache else ""


def spec_for(provenance, *, params: str | Path | None = None, tables: str | Path | None = None,
             table_cache=..., kind: str | None = None):
    """The :class:`~mntes_stream.pipeline.build.ConverterSpec` of a recording's converter.

    Parameters
    ----------
    provenance : Provenance or None
        The recording's provenance (defaults for everything not given).
    params : path, optional
        Detector parameter TOML replacing the recorded parameters.
    tables : path, optional
        Table bank file; its kind becomes the converter kind.
    kind : str, optional
        Converter kind (``core.convert``: ``linear`` for the linear baseline of the same counts)
        instead of the recorded one; not with ``tables`` (a table file sets its own kind). A
        baseline asked for on a recording leaves out the detectors it cannot take (said once).
    table_cache : path, optional
        Where banks built from parameters are kept, as the live converter
        keeps them (``...``: its default, ``~/.cache/mntes-stream/tables``;
        None: always build), and the converter as built (``pipeline/snapshot.py``,
        keyed by the parameters' bytes, kind and software). What comes from the
        cache is what would be built (same identity), in a fraction of the time.
    """
    from mntes_stream.pipeline.build import ConverterSpec

    recorded_kind = provenance.converter_kind if provenance is not None else "table"
    if kind is not None and tables is not None:
        raise ConfigError("a table file sets the converter kind: give the kind or the tables, not both")
    kind = kind or recorded_kind
    text = provenance.params_toml if params is None and provenance is not None else ""
    if tables is not None:  # new tables carry their own parameters; recorded ones would only clash
        return ConverterSpec(kind="", params_file=str(params) if params is not None else "", tables=str(tables))
    if params is None and not text:
        raise ConfigError("the recording has no provenance with detector parameters: give --params (and --tables)")
    return ConverterSpec(kind=kind, params_file=str(params) if params is not None else "", params_toml=text,
                         table_cache=_cache_dir(table_cache) if kind in ("table", "grid") else "",
                         drop_untaken=kind != recorded_kind)


def converter_for(provenance, *, params: str | Path | None = None, tables: str | Path | None = None,
                  table_cache=..., kind: str | None = None):
    """The converter (and its parameters) for a recording: :func:`spec_for` built by ``pipeline.build``.

    Returns
    -------
    converter, params dict, params source (str), tables source (str)

    Raises
    ------
    ConfigError
        Besides the builder's: tables rebuilt from the recorded parameters whose identity is not the
        recorded one (other build options: give the table file).
    """
    from mntes_stream.pipeline.build import build_converter

    spec = spec_for(provenance, params=params, tables=tables, table_cache=table_cache, kind=kind)
    built = build_converter(spec)
    conv = built.converter
    psrc = str(params) if params is not None else "the recording's provenance" if provenance is not None and \
        provenance.params_toml else ""
    if tables is not None:
        return conv, built.params if params is not None else built.bank_params, psrc or "the table file", str(tables)
    tsrc = f"rebuilt from the parameters ({spec.kind})" if spec.kind in ("table", "grid") else "none (analytic)"
    if (provenance is not None and params is None and not spec.drop_untaken and spec.kind in ("table", "grid")
            and provenance.table_identity and str(conv.identity) != provenance.table_identity):
        raise ConfigError(
            f"tables rebuilt from the recorded parameters have identity {str(conv.identity)[:16]}, the recording used "
            f"{provenance.table_identity[:16]} (other build options?): give the table file with --tables"
        )
    return conv, built.params, psrc, tsrc


def convert_recording(source, output: str | Path, *, tables=None, params=None, pipeline_config=None,
                      progress: bool = True, table_cache=..., batch_s: float = 1.0,
                      uncertainty=None, sigma_p: bool = False, only_fused: bool = False,
                      compression: str = _COMPRESSION, kind: str | None = None) -> OfflineStats:
    """Re-convert the recorded counts and housekeeping of ``source`` into ``output`` (MCAP).

    Parameters
    ----------
    source : path, directory or list of paths
        The recording (rotated files are one session).
    output : path
        New MCAP file (never overwritten).
    tables, params : path, optional
        Override the recording's tables / parameters for the whole recording.
        Without them, every recorded calibration converts the part of the
        recording received while it was in force.
    pipeline_config : PipelineConfig, optional
        Alignment and status settings; default: the pipeline's defaults for
        the recording's setup.
    progress : bool
        tqdm progress bar over the input messages.
    table_cache : path, optional
        See :func:`spec_for` (default: the live converter's cache).
    batch_s : float
        > 0 (default 1): the messages of each ``batch_s`` of receive time (and
        at most 64 MiB of them) go through the pipeline together, as a live
        converter's backlog does: the same power and flags as message by
        message, in about 30 % less CPU (longer kernel rows, fewer calls), with
        the outputs stamped at each batch's last message and a status at most
        once per batch. 0: message by message, each output stamped with the
        receive time of the message that released it.
    uncertainty : core.uncertainty.UncertaintySettings, optional
        Given: LOW_RESPONSIVITY flagged, as a live converter with this ``[uncertainty]``
        table flags it (``mntes-stream convert`` passes the converter config's, or the
        defaults': on); None: not.
    sigma_p : bool
        With ``uncertainty``: sigma_P in every power chunk too, as ``[converter] sigma_p = true``.
    only_fused : bool
        LOW_RESPONSIVITY only where the converter flags it in its own pass (``ConverterPipeline``;
        ``[converter] low_responsivity = "auto"``).
    compression : {"lz4", "zstd", "none"}
        The output's chunk compression (default lz4: the cheapest to write and read; zstd: smaller files).
    kind : str, optional
        Convert with this converter kind (e.g. ``linear``: the linear baseline of the same counts) and the
        recorded parameters, instead of each calibration's recorded kind (see :func:`spec_for`).
    """
    from collections import Counter

    from tqdm import tqdm

    from mntes_stream.io import keys
    from mntes_stream.io.mcap import McapFileWriter, Session, writer_description
    from mntes_stream.pipeline.config import INPUT_KINDS, PipelineConfig, input_topics
    from mntes_stream.pipeline.pipeline import ConverterPipeline
    from mntes_stream.pipeline.runner import Runner

    if not batch_s >= 0:
        raise ConfigError(f"batch_s must be >= 0, got {batch_s}")
    t_start = time.monotonic()
    session = Session(source)
    calibrations = recorded_calibrations(session)
    if pipeline_config is None:
        setup = calibrations[-1][1].setup if calibrations else None
        if setup is None:
            setups = {_setup_of(t) for t in session.message_counts() if keys.kind_of(t) in INPUT_KINDS} - {None}
            if len(setups) != 1:
                raise ConfigError(f"cannot tell the setup of the recording (found {sorted(setups)})")
            setup = setups.pop()
        pipeline_config = PipelineConfig(setup=setup)
    calibrations = [(t, prov) for t, prov in calibrations if prov.setup == pipeline_config.setup]
    prov = calibrations[-1][1] if calibrations else None
    # Every converter is built (and checked against its recorded identity) before the output exists.
    if params is not None or tables is not None or len(calibrations) <= 1:
        if len(calibrations) > 1:
            log.warning("the recording holds %d calibrations (changed at log times %s); the given %s replace all of them",
                        len(calibrations), [t for t, _ in calibrations[1:]], "tables" if tables is not None else "parameters")
        plan = [(None, converter_for(prov, params=params, tables=tables, table_cache=table_cache, kind=kind))]
    else:
        built: dict[tuple, tuple] = {}  # a calibration that comes back is not rebuilt
        plan = []
        for k, (t_ns, p) in enumerate(calibrations):
            if _calibration(p) not in built:
                built[_calibration(p)] = converter_for(p, table_cache=table_cache, kind=kind)
            plan.append((t_ns if k else None, built[_calibration(p)]))
        log.info("the calibration changed %d time(s) during the recording: each part converted with its own", len(plan) - 1)
    converter, pdict, psrc, tsrc = plan[-1][1]
    selection = list(input_topics(pipeline_config.setup))
    total = session.count(selection)
    n_in = n_power = n_status = 0
    meta = writer_description(
        mode="offline conversion", input=[str(f.path) for f in session.files], params_source=psrc, tables_source=tsrc,
        calibrations=str(len(plan)),
    )
    totals = {"samples_converted": 0, "chunks_lost": 0}
    bad, flag_counts = Counter(), Counter()
    ledger = Ledger("converted")

    def add_status(pipe) -> None:
        ledger.merge(pipe.ledger_now())
        status = pipe.status()
        totals["samples_converted"] += status.samples_converted
        totals["chunks_lost"] += status.chunks_lost
        bad.update(status.bad_messages)
        flag_counts.update(status.flag_counts)

    # whole: OUT appears only once finished; a failure (a full disk) leaves no file that looks complete.
    with McapFileWriter(output, metadata={"mntes.recording": meta}, whole=True, compression=compression,
                        chunk_size_bytes=_CHUNK_BYTES) as out:
        bar = tqdm(total=total, unit="msg", desc="convert", disable=not progress)

        def start_pipeline(k):
            conv, pd = plan[k][1][:2]
            return ConverterPipeline(conv, pipeline_config, params=pd, clock=None, uncertainty=uncertainty,
                                     sigma_p=sigma_p, only_fused=only_fused)

        # The inputs are written back with the outputs, in the runner's order; each calibration's pipeline
        # starts with its provenance; batches as a live converter takes its backlog (batch_s > 0: the same
        # power and flags as message by message, stamped at each batch's last message).
        runner = Runner(start_pipeline, switches=[t for t, _ in plan[1:]], batch_s=batch_s, batch_bytes=_BATCH_BYTES,
                        inputs=True, provenance=True, retire=add_status)

        def emit(writes):
            nonlocal n_power, n_status
            for key, payload, t_ns in writes:
                out.write(key, payload, t_ns)
                kind = keys.kind_of(key)
                n_power += kind == "power"
                n_status += kind == "status"

        for msg in session.iter_messages(selection):
            emit(runner.feed(msg.topic, msg.payload, msg.log_time_ns))
            n_in += 1
            bar.update(1)
        emit(runner.finish())
        bar.close()
        _mark_damage(session, out)
    return OfflineStats(
        input_messages=n_in,
        power_chunks=n_power,
        status_messages=n_status,
        samples_converted=totals["samples_converted"],
        bad_messages={k: v for k, v in bad.items() if v},
        chunks_lost=totals["chunks_lost"],
        converter_kind=str(converter.kind),
        table_identity=str(converter.identity),
        recorded_table_identity=prov.table_identity if prov is not None else "",
        params_source=psrc,
        tables_source=tsrc,
        output=str(output),
        duration_s=time.monotonic() - t_start,
        input_complete=session.complete,
        flag_counts={k: v for k, v in flag_counts.items() if v},
        calibrations=len(plan),
        ledger=ledger.as_dict(),
        ledger_line=ledger.line(),
        damaged=session.damage_line(),
        damaged_messages=session.damaged_messages + session.unlabelled_messages,
    )


def _mark_damage(session, out) -> None:
    """The input's unreadable chunks (and its own recorded losses) as ``mntes.damaged`` records of the output."""
    from mntes_stream.io.mcap.repair import DAMAGE_METADATA, damage_metadata

    for m in session.metadata():
        if m.name == DAMAGE_METADATA:  # the input was itself made from a damaged file (recover)
            out.add_metadata(DAMAGE_METADATA, {**m.data, "inherited_from": m.path})
    if session.damage or session.unlabelled_messages:
        out.add_metadata(DAMAGE_METADATA, damage_metadata(session.damage, session.unlabelled_messages))


def _setup_of(topic: str) -> str | None:
    from mntes_stream.io import keys

    try:
        return keys.parse_key(topic)["setup"]
    except ConfigError:
        return None
