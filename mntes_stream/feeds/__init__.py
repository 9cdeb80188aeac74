"""Feeds for downstream mapmaking: recorded or live power as numpy, and HDF5 export.

- :func:`read_power`, :class:`RecordedPower`, :func:`iter_power_blocks`: MCAP
  sessions (a file, rotated files, a directory) to :class:`TodBlock`
  (time-ordered data: ``p_opt_w`` detectors x samples in W, ``t_ns``,
  ``flags``, ``detectors``, ``table_identities``).
- :class:`LivePowerFeed`: the same blocks from zenoh as they are published.
- :func:`export_hdf5` / :func:`read_hdf5`: one HDF5 group per observation
  (module) with ``tod``, ``time``, ``time_ns``, ``flags``, ``detectors`` and
  provenance attributes (this package's layout, read with h5py).
- :mod:`mntes_stream.feeds.frameworks`: ``toast.Observation``, sotodlib
  ``AxisManager`` and ``litebird_sim.Observation`` objects, and files written
  by those frameworks' own writers (``RecordedPower.to_framework``,
  ``LivePowerFeed.to_framework``, ``export --format``).

Missing chunks are NaN + ``flags.GAP`` and absent detectors NaN +
``flags.UNKNOWN_CHANNEL``: never silent zeros. A step in time beyond
``max_gap_s`` (default 1 h) is a reported segment break, not a hole to fill.
"""

from mntes_stream.feeds.blocks import StreamId, StreamStats, TodBlock
from mntes_stream.feeds.hdf5 import ExportSummary, export_hdf5, read_hdf5
from mntes_stream.feeds.live import LivePowerFeed
from mntes_stream.feeds.recorded import RecordedPower, iter_power_blocks, read_power

__all__ = [
    "TodBlock",
    "StreamId",
    "StreamStats",
    "RecordedPower",
    "read_power",
    "iter_power_blocks",
    "LivePowerFeed",
    "ExportSummary",
    "export_hdf5",
    "read_hdf5",
]
