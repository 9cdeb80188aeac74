"""Building a converter, one way for every path: :func:`build_converter` of a :class:`ConverterSpec`.

The converter service's config, a recording's provenance (offline ``convert``)
and the G3 module each give a spec; the builder takes the converter from its
snapshot (``pipeline.snapshot``: the converter as an earlier build made it,
keyed by the parameters' bytes, kind, part and software), else builds it,
taking its table bank from the table file, the table cache or a build (then
kept in the cache). Banks are kept in the table cache
(``~/.cache/mntes-stream/tables`` by default) under a key of the parameters,
kind, table format, software version and the core's source digest
(:func:`~mntes_stream.pipeline.snapshot.build_fingerprint`), so a bank built by
other code is never reused.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

from mntes_stream import cache_root
from mntes_stream.errors import ConfigError
from mntes_stream.io.cache import DEFAULT_MAX_MB

__all__ = ["BuiltConverter", "ConverterSpec", "build_converter", "cached_bank", "default_table_cache", "owned",
           "owned_part"]

log = logging.getLogger("mntes_stream.converter")


def default_table_cache() -> str:
    """The table cache the converter service and offline ``convert`` use unless told otherwise."""
    return os.path.join(cache_root(), "tables")


def cached_bank(kind: str, params: dict, table_cache: str, max_mb: float = DEFAULT_MAX_MB):
    """The bank of ``kind`` for ``params`` from the cache, or built and put there (a broken entry is rebuilt).

    Parameters
    ----------
    kind : {"table", "grid"}
    params : dict of str to DetectorParams
    table_cache : str
        The cache directory (``~`` expanded).
    max_mb : float
        The cache's size cap: after a write the least recently used entries beyond it are removed.
    """
    from mntes_stream import __version__
    from mntes_stream.core.tables import TABLE_FORMAT, build_bank, params_identity
    from mntes_stream.errors import MntesError
    from mntes_stream.io.cache import prune, touch
    from mntes_stream.io.tablefile import load_bank, save_bank
    from mntes_stream.pipeline.snapshot import build_fingerprint

    key = params_identity(list(params.values()), {"kind": kind, "format": TABLE_FORMAT, "software": __version__,
                                                  "code": build_fingerprint()})
    directory = Path(os.path.expanduser(table_cache))
    path = directory / f"{kind}-{key[:32]}.npz"
    if path.exists():
        try:
            bank = load_bank(path)  # verifies the content hash: a damaged entry is not used
            log.info("table bank %s from the cache %s", bank.identity[:12], path)
            touch(path)  # recently used: the last the size cap removes
            return bank
        except MntesError as exc:
            log.warning("table cache entry %s unusable (%s): rebuilding", path, exc)
    bank = build_bank(params, kind=kind)
    try:
        directory.mkdir(parents=True, exist_ok=True)
        save_bank(bank, path)
        prune(directory, max_mb * 1e6, keep=(path,))
    except OSError as exc:  # a read-only home must not stop the converter
        log.warning("cannot write the table cache %s: %s", path, exc)
    return bank


# ---------------------------------------------------------------------------------------------- the one builder

#: make_converter options a ready bank takes (the rest build the bank: then it is built, not taken from the cache).
_RUN_OPTIONS = frozenset({"backend", "bias_rtol", "readout_noise_a"})
GRADIENTS = ("no", "yes", "if_fused")


@dataclass(frozen=True)
class ConverterSpec:
    """What a converter is built from: the one input of :func:`build_converter`.

    The converter service's config gives one (``ConverterConfig.spec``), so does a
    recording's provenance (``pipeline.offline.spec_for``) and the G3 module
    (``g3.power.OpticalPower``). At most one source of parameters is named.

    Parameters
    ----------
    kind : str
        A converter kind (``core.convert.CONVERTER_KINDS``); ``""`` with ``tables``: the table file's kind.
    params_file : str
        A detector parameter file (TOML).
    params_toml : str
        Parameter TOML text (a recording's provenance).
    params : tuple of (str, DetectorParams)
        Parameters given in memory, keyed by detector id (the G3 module: the wired bolometers').
    tables : str
        A table bank file (its parameters, unless parameters are named too).
    table_cache : str
        Where banks built from parameters, and the converter as built (``pipeline.snapshot``), are
        kept ("" = no cache). Parameters in memory have no snapshot (no file bytes to key it by).
    table_cache_max_mb : float
        The cache's size cap.
    boards, modules, shard : the part of the focal plane owned (``core.shards``): only its
        parameters are taken.
    drop_untaken : bool
        A baseline kind asked for on parameters that were not built for it: detectors not in the
        transition at their nominal operating point are left out (power NaN, UNKNOWN_CHANNEL), said once.
    gradients : {"no", "yes", "if_fused"}
        Solve the nominal gradients (LOW_RESPONSIVITY, sigma_P) now, so the snapshot keeps them;
        ``if_fused``: when the converter flags LOW_RESPONSIVITY in its own pass.
    options : tuple of (str, object)
        ``core.convert.make_converter`` options (build options bypass the bank cache).
    """

    kind: str = "table"
    params_file: str = ""
    params_toml: str = ""
    params: tuple = ()
    tables: str = ""
    table_cache: str = ""
    table_cache_max_mb: float = DEFAULT_MAX_MB
    boards: tuple[int, ...] = ()
    modules: tuple[int, ...] = ()
    shard: str = ""
    drop_untaken: bool = False
    gradients: str = "no"
    options: tuple = ()

    def __post_init__(self):
        named = [n for n in ("params_file", "params_toml", "params") if getattr(self, n)]
        if len(named) > 1:
            raise ConfigError(f"a converter spec names its parameters once, got {' and '.join(named)}")
        if not self.kind and not self.tables:
            raise ConfigError("a converter spec without tables needs its kind")
        if self.gradients not in GRADIENTS:
            raise ConfigError(f"gradients must be one of {GRADIENTS}, got {self.gradients!r}")

    @property
    def partial(self) -> bool:
        """True when the converter owns part of the focal plane (boards, modules or a shard)."""
        from mntes_stream.core.shards import Shard

        return bool(self.boards or self.modules or not Shard.parse(self.shard).whole)


@dataclass(frozen=True)
class BuiltConverter:
    """What :func:`build_converter` gives.

    Attributes
    ----------
    converter : core.convert.Converter
    params : dict of str to DetectorParams, or None
        The parameters it was built from (the owned part); None: a table bank's own.
    streams : list of (board, module), or None
        The streams owned; None when the detector ids do not name their board and module (every stream).
    bank_params : dict of str to DetectorParams, or None
        With a table file and no parameters named: the bank's (what its provenance names).
    from_snapshot : bool
        Loaded as an earlier build saved it (``pipeline.snapshot``).
    params_toml : str or None
        From a snapshot: the parameters as ``params_to_toml`` wrote them (the provenance's text, not written
        again); None: not at hand.
    """

    converter: object
    params: dict | None
    streams: list | None
    bank_params: dict | None = None
    from_snapshot: bool = False
    params_toml: str | None = None


def _read_params(spec: ConverterSpec) -> dict | None:
    if spec.params_file:
        from mntes_stream.io.paramfile import load_params

        return load_params(spec.params_file)
    if spec.params_toml:
        import tomllib

        from mntes_stream.io.paramfile import parse_params

        try:
            return parse_params(tomllib.loads(spec.params_toml), "recorded provenance")
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"recorded provenance: parameter TOML unreadable: {exc}") from None
    return dict(spec.params) if spec.params else None


def owned(spec: ConverterSpec, params: dict | None, ids) -> tuple[dict | None, list | None]:
    """The parameters of the part of the focal plane ``spec`` owns, and its ``(board, module)`` streams.

    ``ids``: every detector id there is (the parameters', else the table bank's). Streams are None
    when the ids do not name their board and module (then the converter takes every stream, unsharded).
    """
    from mntes_stream.core.ids import parse_detector_id
    from mntes_stream.core.shards import Shard, owned_streams
    from mntes_stream.pipeline.housekeeping import known_modules

    modules = known_modules(ids)
    if modules is None:
        if spec.partial:
            raise ConfigError("boards, modules and shard need detector ids of the form b<board>m<module>c<channel>")
        return params, None
    shard = Shard.parse(spec.shard)
    streams = owned_streams(modules, shard, spec.boards, spec.modules)
    if spec.partial and not streams:
        raise ConfigError(f"boards {list(spec.boards) or '*'}, modules {list(spec.modules) or '*'}, shard "
                          f"{shard}: no stream of the parameters is in that part of the focal plane")
    if params is not None and spec.partial:
        wanted = set(streams)
        params = {d: p for d, p in params.items() if parse_detector_id(d)[:2] in wanted}
    return params, streams


def owned_part(spec: ConverterSpec) -> tuple[dict | None, list | None]:
    """:func:`owned` of the parameters ``spec`` names (or of its table file's detectors)."""
    params = _read_params(spec)
    if params is not None:
        return owned(spec, params, params.keys())
    from mntes_stream.io.tablefile import load_bank

    return owned(spec, None, load_bank(spec.tables).params_by_id())


def _drop_untaken(kind: str, params: dict) -> dict:
    """A baseline's parameters: detectors not in the transition at their nominal operating point left out."""
    from mntes_stream.core.convert import baseline_can_take

    left = sorted(d for d, q in params.items() if not baseline_can_take(q))
    if left and len(left) == len(params):
        raise ConfigError(f"no detector is in the transition at its nominal operating point: no {kind} baseline")
    if left:
        log.warning("%s baseline: %d detector(s) not in the transition at their nominal operating point left out "
                    "(power NaN, UNKNOWN_CHANNEL): %s", kind, len(left),
                    ", ".join(left[:8]) + (" ..." if len(left) > 8 else ""))
    return {d: q for d, q in params.items() if d not in left}


def build_converter(spec: ConverterSpec, building=None) -> BuiltConverter:
    """The converter ``spec`` names: from its snapshot, else built (its bank from the table file, the cache,
    or built and cached) and kept as a snapshot for the next time.

    Parameters
    ----------
    spec : ConverterSpec
    building : callable, optional
        ``building(text)``: a context manager around the build (not a snapshot load), e.g. the
        service's ``announced(ctx.progress, ...)``; ``text`` says what is built.

    Raises
    ------
    ConfigError
        Unreadable parameters or tables, no parameters at all, a part of the focal plane with no stream,
        parameters that disagree with the table file.
    """
    import contextlib

    from mntes_stream.core.convert import BASELINE_KINDS, make_converter
    from mntes_stream.pipeline.snapshot import load_snapshot, save_snapshot

    key, snap = load_snapshot(spec)
    if snap is not None:
        params, streams, conv, text = snap
        return BuiltConverter(conv, params, streams, _bank_params(spec, params, conv), True, text)
    params = _read_params(spec)
    bank = None
    if spec.tables:
        from mntes_stream.io.tablefile import load_bank

        bank = load_bank(spec.tables)
    if params is None and bank is None:
        raise ConfigError("give detector parameters or a table bank file")
    params, streams = owned(spec, params, params.keys() if params is not None else bank.params_by_id())
    kind = spec.kind or bank.kind
    if spec.drop_untaken and kind in BASELINE_KINDS and params:
        params = _drop_untaken(kind, params)
    options = dict(spec.options)
    what = f"{len(params)} detectors" if params is not None else "the table bank"
    with (building or (lambda text: contextlib.nullcontext()))(
            f"building the {kind} converter for {what} (tables, flag thresholds; kept in "
            f"{spec.table_cache or 'no cache'} for the next start)"):
        if bank is None and spec.table_cache and kind in ("table", "grid") and params and \
                not set(options) - _RUN_OPTIONS:
            bank = cached_bank(kind, params, spec.table_cache, spec.table_cache_max_mb)
        conv = make_converter(kind, params, bank, **options)
        if spec.gradients == "yes" or (spec.gradients == "if_fused" and getattr(conv, "fuses_low_responsivity",
                                                                                False)):
            from mntes_stream.core.uncertainty import nominal_gradients

            nominal_gradients(conv)  # solved once, kept in the snapshot (ms per detector)
    save_snapshot(spec, key, params, streams, conv)
    return BuiltConverter(conv, params, streams, _bank_params(spec, params, conv), False)


def _bank_params(spec: ConverterSpec, params, conv) -> dict | None:
    """A table file's parameters when no others were named (what a conversion with it names)."""
    if params is not None or not spec.tables:
        return None
    return dict(zip(conv.detector_ids, conv.params))
