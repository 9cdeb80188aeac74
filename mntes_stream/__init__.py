"""mntes-stream: real-time MNTES conversion of DfMux TES readout to optical power.

Layout (data flows top to bottom; see README "What it is"):

- ``mntes_stream.core``: pure computation on numpy arrays, no I/O: physics
  (``params``, ``transition``, ``model``), tables and conversion (``tables``,
  ``convert``), housekeeping alignment (``align``), flags, the simulator and
  validation study (``sim``, ``validation``), ground calibration (``calib``).
- ``mntes_stream.io``: the edges: parameter and table files, msgpack codec and
  messages, MCAP, zenoh transport.
- ``mntes_stream.service``: the converter pipeline and the services around it
  (converter, simulator/source, recorder, replay, offline conversion).
- ``mntes_stream.feeds``, ``mntes_stream.monitor``: mapmaking feeds and the
  quick-look page.
- ``mntes_stream.cli``, ``mntes_stream.bench``: the ``mntes-stream`` command.
"""

__version__ = "0.1.0"


def cache_root() -> str:
    """The user's cache of mntes-stream: table banks, converter snapshots, compiled kernels.

    ``$MNTES_STREAM_CACHE`` if set, else ``$XDG_CACHE_HOME/mntes-stream`` (``~/.cache/mntes-stream``);
    never inside the installed package. ``mntes-stream cache`` shows and clears it.
    """
    import os

    own = os.environ.get("MNTES_STREAM_CACHE")
    if own:
        return os.path.expanduser(own)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "mntes-stream")
