"""The converter, free of zenoh: messages in, power, status and provenance out (no sockets, no processes).

Below ``service/`` (which runs it as the converter service) and ``g3/``
(which runs it inside a spt3g pipeline); it imports only ``core``, ``io`` and
``errors``. docs/architecture.md, "Layers" and "Data flow".

- :mod:`.config`: :class:`PipelineConfig` (the ``[alignment]`` table, keys, status cadence).
- :mod:`.items`: what flows between the stages, and ``Stages``, the named list checked by what each takes and gives.
- :mod:`.stages`, :mod:`.convert`, :mod:`.status`: the stages; :mod:`.housekeeping`: the histories they align with.
- :mod:`.pipeline`: :class:`ConverterPipeline`, the stages run in order.
- :mod:`.runner`: :class:`Runner`, what every driver feeds (batching, ticks, late power, flush, calibration switches).
- :mod:`.build`: :func:`build_converter` of a :class:`ConverterSpec`, the table cache;
  :mod:`.snapshot`: the converter as built, kept on disk.
- :mod:`.offline`: a recording through the same runner (``convert``).

The names below are imported on first use (``import mntes_stream.pipeline`` loads
nothing else); the modules of this package import one another, never this ``__init__``.
"""

from __future__ import annotations

__all__ = ["ConverterPipeline", "ConverterSpec", "PipelineConfig", "Runner", "build_converter"]

_WHERE = {"ConverterPipeline": "pipeline", "PipelineConfig": "config", "Runner": "runner", "ConverterSpec": "build",
          "build_converter": "build"}


def __getattr__(name: str):
    where = _WHERE.get(name)
    if where is None:
        raise AttributeError(f"module 'mntes_stream.pipeline' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(f"{__name__}.{where}"), name)
