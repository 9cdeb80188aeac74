"""Foxglove: a setup live over the Foxglove WebSocket protocol, and json channels in MCAP files.

``translate`` (mntes messages -> json messages with JSON Schemas; no foxglove
import), ``transcode`` (json channels beside the msgpack originals
of a recording; ``mntes-stream transcode --foxglove`` and the recorder's
``foxglove_channels``). The ``foxglove`` registry service (foxglove-sdk, the
``foxglove`` extra) is :mod:`mntes_stream.service.foxglove`: the recorder
uses ``transcode``, so this package sits below ``service/``.
"""
