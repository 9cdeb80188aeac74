"""Quick-look monitor: a live web page (or terminal table) of a running setup.

Layout follows the stream's flow: ``analysis`` and ``aggregate`` are the pure
core (ring buffers, decimation, spectra, channel states, health; no I/O),
``subscriber`` is the zenoh edge, ``server`` the web edge (aiohttp, page in
``static/``), ``text`` the terminal table. ``mntes-stream monitor`` wires them.
"""

from mntes_stream.monitor.aggregate import STATE_NAMES, Aggregator, MonitorConfig

__all__ = ["Aggregator", "MonitorConfig", "STATE_NAMES"]
