"""The one registry of long-running services: config table name -> :class:`~mntes_stream.service.base.Service`.

``serve`` picks a config file's service by its main table, ``up`` and
:class:`~mntes_stream.service.supervise.Services` start services by name.
A new service is one module and one line here.
"""

from __future__ import annotations

from mntes_stream.dfmux.bridge import DfMuxBridgeService
from mntes_stream.errors import ConfigError
from mntes_stream.foxglove.service import FoxgloveService
from mntes_stream.g3.bridge import G3BridgeService
from mntes_stream.monitor.service import MonitorService
from mntes_stream.ocs.bridge import OcsBridgeService
from mntes_stream.service.base import Service
from mntes_stream.service.converter import ConverterService
from mntes_stream.service.recorder import RecorderService
from mntes_stream.service.replay import ReplayService
from mntes_stream.service.router import RouterService
from mntes_stream.service.simulator import SimulatorService
from mntes_stream.service.source import SourceService

__all__ = ["SERVICES", "service_class"]

SERVICES: dict[str, type[Service]] = {cls.name: cls for cls in (
    ConverterService,
    SourceService,
    SimulatorService,
    RecorderService,
    ReplayService,
    MonitorService,
    FoxgloveService,
    RouterService,
    G3BridgeService,
    DfMuxBridgeService,
    OcsBridgeService,
)}


def service_class(name: str) -> type[Service]:
    """The service registered as ``name``; ConfigError naming the known ones otherwise."""
    try:
        return SERVICES[name]
    except KeyError:
        raise ConfigError(f"unknown service {name!r} (known: {', '.join(SERVICES)})") from None
