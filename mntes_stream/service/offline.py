"""Offline re-conversion of a recording through the live converter's own pipeline.

The recorded counts and housekeeping are fed to
:class:`~mntes_stream.service.pipeline.ConverterPipeline` in log-time order
with their recorded receive times, exactly as the live service feeds what its
subscriber receives; the inputs and everything the pipeline emits (power,
status, its provenance) are written to the output file. Outputs are stamped
with the receive time of the message that produced them (``clock=None``), so
running the conversion twice gives identical files' contents.

Parameters and tables default to the recording's own provenance (the latest
``mntes.provenance`` attachment): detector parameters from its TOML text, the
converter kind from it, and for table kinds a table bank rebuilt from those
parameters whose identity must match the recorded one. ``tables`` (a table
file) and ``params`` (a parameter TOML) override them, e.g. with a newer
calibration.
"""

from __future__ import annotations

import logging
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from mntes_stream.errors import ConfigError

__all__ = ["OfflineStats", "build_converter", "convert_recording"]

log = logging.getLogger("mntes_stream.offline")


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

    def summary(self) -> str:
        same = "same tables as recorded" if self.table_identity == self.recorded_table_identity else \
            f"recorded tables were {self.recorded_table_identity[:16] or 'unknown'}"
        bad = ", ".join(f"{k}={v}" for k, v in self.bad_messages.items() if v) or "none"
        return (f"converted {self.samples_converted / 1e6:.3f} Msamples in {self.power_chunks} power chunks from "
                f"{self.input_messages} recorded inputs in {self.duration_s:.1f} s -> {self.output}\n"
                f"  converter {self.converter_kind}, tables {self.table_identity[:16]} ({same})\n"
                f"  params: {self.params_source}; tables: {self.tables_source}; bad messages: {bad}"
                + ("" if self.input_complete else "\n  input was not finished by its recorder: converted what was recovered"))


def _recorded_provenance(source):
    from mntes_stream.io.mcap_io import latest_provenance
    from mntes_stream.io.messages import Provenance

    raw = latest_provenance(source)
    return None if raw is None else Provenance.from_bytes(raw)


def build_converter(provenance, *, params: str | Path | None = None, tables: str | Path | None = None):
    """The converter (and its parameters) for a recording.

    Parameters
    ----------
    provenance : Provenance or None
        The recording's provenance (defaults for everything not given).
    params : path, optional
        Detector parameter TOML replacing the recorded parameters.
    tables : path, optional
        Table bank file; its kind becomes the converter kind.

    Returns
    -------
    converter, params dict, params source (str), tables source (str)
    """
    from mntes_stream.core.convert import make_converter
    from mntes_stream.io.paramfile import load_params, parse_params

    if params is not None:
        pdict, psrc = load_params(params), str(params)
    elif provenance is not None and provenance.params_toml:
        try:
            pdict = parse_params(tomllib.loads(provenance.params_toml), "recorded provenance")
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"recorded provenance: parameter TOML unreadable: {exc}") from None
        psrc = "the recording's provenance"
    else:
        pdict, psrc = None, ""
    if tables is not None:
        from mntes_stream.io.tablefile import load_bank

        bank = load_bank(tables)
        # New tables carry their own parameters; recorded ones would only clash.
        conv = make_converter(bank.kind, pdict if params is not None else None, bank=bank)
        return conv, (pdict if params is not None else bank.params_by_id()), psrc or "the table file", str(tables)
    if pdict is None:
        raise ConfigError("the recording has no provenance with detector parameters: give --params (and --tables)")
    kind = provenance.converter_kind if provenance is not None else "table"
    conv = make_converter(kind, pdict)
    tsrc = f"rebuilt from the parameters ({kind})" if kind in ("table", "grid") else "none (analytic)"
    if provenance is not None and params is None and kind in ("table", "grid") and str(conv.identity) != provenance.table_identity:
        raise ConfigError(
            f"tables rebuilt from the recorded parameters have identity {str(conv.identity)[:16]}, the recording used "
            f"{provenance.table_identity[:16]} (other build options?): give the table file with --tables"
        )
    return conv, pdict, psrc, tsrc


def convert_recording(source, output: str | Path, *, tables=None, params=None, pipeline_config=None,
                      progress: bool = True) -> OfflineStats:
    """Re-convert the recorded counts and housekeeping of ``source`` into ``output`` (MCAP).

    Parameters
    ----------
    source : path, directory or list of paths
        The recording (rotated files are one session).
    output : path
        New MCAP file (never overwritten).
    tables, params : path, optional
        Override the recording's tables / parameters.
    pipeline_config : PipelineConfig, optional
        Alignment and status settings; default: the pipeline's defaults for
        the recording's setup.
    progress : bool
        tqdm progress bar over the input messages.
    """
    from tqdm import tqdm

    from mntes_stream.io import keys
    from mntes_stream.io.mcap_io import McapFileWriter, Session, writer_description
    from mntes_stream.service.pipeline import ConverterPipeline, PipelineConfig
    from mntes_stream.service.replay import INPUT_TOPICS

    t_start = time.monotonic()
    session = Session(source)
    prov = _recorded_provenance(source)
    converter, pdict, psrc, tsrc = build_converter(prov, params=params, tables=tables)
    if pipeline_config is None:
        setup = prov.setup if prov is not None else None
        if setup is None:
            setups = {t.split("/")[1] for t in session.message_counts() if t.count("/") >= 2}
            if len(setups) != 1:
                raise ConfigError(f"cannot tell the setup of the recording (found {sorted(setups)})")
            setup = setups.pop()
        pipeline_config = PipelineConfig(setup=setup)
    pipe = ConverterPipeline(converter, pipeline_config, params=pdict, clock=None)
    selection = [t.replace("*", pipeline_config.setup, 1) for t in INPUT_TOPICS]
    total = session.count(selection)
    n_in = n_power = n_status = 0
    meta = writer_description(
        mode="offline conversion", input=[str(f.path) for f in session.files], params_source=psrc, tables_source=tsrc
    )
    with McapFileWriter(output, metadata={"mntes.recording": meta}) as out:
        bar = tqdm(total=total, unit="msg", desc="convert", disable=not progress)
        t_last = None

        def emit(items, t_ns):
            nonlocal n_power, n_status
            for key, payload in items:
                out.write(key, payload, t_ns)
                kind = key.split("/")[2]
                n_power += kind == "power"
                n_status += kind == "status"

        for msg in session.iter_messages(selection):
            if t_last is None:
                out.write(keys.provenance_key(pipeline_config.setup), pipe.provenance_bytes(), msg.log_time_ns)
            t_last = msg.log_time_ns
            # Release what waited long enough *before* this message, as the live service's ticks do.
            emit(pipe.tick(msg.log_time_ns), msg.log_time_ns)
            out.write(msg.topic, msg.payload, msg.log_time_ns)
            emit(pipe.handle(msg.topic, msg.payload, msg.log_time_ns), msg.log_time_ns)
            n_in += 1
            bar.update(1)
        if t_last is not None:
            emit(pipe.flush(), t_last)
        bar.close()
    status = pipe.status()
    return OfflineStats(
        input_messages=n_in,
        power_chunks=n_power,
        status_messages=n_status,
        samples_converted=status.samples_converted,
        bad_messages={k: v for k, v in status.bad_messages.items() if v},
        chunks_lost=status.chunks_lost,
        converter_kind=str(converter.kind),
        table_identity=str(converter.identity),
        recorded_table_identity=prov.table_identity if prov is not None else "",
        params_source=psrc,
        tables_source=tsrc,
        output=str(output),
        duration_s=time.monotonic() - t_start,
        input_complete=session.complete,
        flag_counts={k: v for k, v in status.flag_counts.items() if v},
    )
