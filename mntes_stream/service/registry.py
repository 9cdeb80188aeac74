"""The one registry of long-running services: config table name -> :class:`~mntes_stream.service.base.Service`.

``serve`` picks a config file's service by its main table, ``up`` and
:class:`~mntes_stream.service.supervise.Services` start services by name.
A new service is one module and one line here.

Entries name their class as ``"module:Class"`` (as an entry point does),
imported on first lookup: services of edge packages (``g3``, ``dfmux``,
``ocs``, ``foxglove``, ``monitor``) build on ``service.base``, so a
registry importing them would make ``service/`` depend on the packages
above it (the cycle ``g3.bridge -> service.config -> service.registry ->
g3.bridge``). tests/test_layering.py checks both the contract and that
every entry resolves to a class registered under its own name.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterator, Mapping

from mntes_stream.errors import ConfigError
from mntes_stream.service.base import Service

__all__ = ["ENTRIES", "SERVICES", "service_class"]

ENTRIES: dict[str, str] = {
    "converter": "mntes_stream.service.converter:ConverterService",
    "source": "mntes_stream.service.source:SourceService",
    "simulator": "mntes_stream.service.simulator:SimulatorService",
    "recorder": "mntes_stream.service.recorder:RecorderService",
    "replay": "mntes_stream.service.replay:ReplayService",
    "monitor": "mntes_stream.monitor.service:MonitorService",
    "foxglove": "mntes_stream.service.foxglove:FoxgloveService",
    "router": "mntes_stream.service.router:RouterService",
    "g3-bridge": "mntes_stream.g3.bridge:G3BridgeService",
    "dfmux-bridge": "mntes_stream.dfmux.bridge:DfMuxBridgeService",
    "ocs-bridge": "mntes_stream.ocs.bridge:OcsBridgeService",
}


class _Registry(Mapping[str, type[Service]]):
    """Name -> service class, each class imported when first looked up."""

    def __init__(self, entries: Mapping[str, str]):
        self._entries = dict(entries)
        self._loaded: dict[str, type[Service]] = {}

    def __getitem__(self, name: str) -> type[Service]:
        if name not in self._loaded:
            module, _, attr = self._entries[name].partition(":")
            self._loaded[name] = getattr(importlib.import_module(module), attr)
        return self._loaded[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def __len__(self) -> int:
        return len(self._entries)


SERVICES: Mapping[str, type[Service]] = _Registry(ENTRIES)


def service_class(name: str) -> type[Service]:
    """The service registered as ``name``; ConfigError naming the known ones otherwise."""
    if name not in ENTRIES:
        raise ConfigError(f"unknown service {name!r} (known: {', '.join(ENTRIES)})")
    return SERVICES[name]
