"""The converter, free of zenoh: messages in, power, status and provenance out (no sockets, no processes).

Below ``service/`` (which runs it as the converter service) and ``g3/``
(which runs it inside a spt3g pipeline); it imports only ``core``, ``io`` and
``errors``. docs/architecture.md, "Layers" and "Data flow".

- :mod:`.config`: :class:`PipelineConfig` (the ``[alignment]`` table, keys, status cadence).
- :mod:`.stages`, :mod:`.convert`, :mod:`.status`: the stages; :mod:`.housekeeping`: the histories they align with.
- :mod:`.pipeline`: :class:`ConverterPipeline`, the stages run in order.
- :mod:`.build`: the table cache; :mod:`.snapshot`: the converter as built, kept on disk.
- :mod:`.offline`: a recording through the same pipeline (``convert``).

The names below are imported on first use (``import mntes_stream.pipeline`` loads
nothing else); the modules of this package import one another, never this ``__init__``.
"""

from __future__ import annotations

__all__ = ["ConverterPipeline", "PipelineConfig"]

_WHERE = {"ConverterPipeline": "pipeline", "PipelineConfig": "config"}


def __getattr__(name: str):
    where = _WHERE.get(name)
    if where is None:
        raise AttributeError(f"module 'mntes_stream.pipeline' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(f"{__name__}.{where}"), name)
