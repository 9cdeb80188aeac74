"""mntes-stream: real-time MNTES conversion of DfMux TES readout to optical power.

Layout (data flows top to bottom):

- ``mntes_stream.core``: pure computation on numpy arrays, no I/O. Physics
  (``params``, ``transition``, ``model``), and later tables, conversion, alignment.
- ``mntes_stream.io``: the edges: parameter files, msgpack codec, MCAP, zenoh.
- ``mntes_stream.cli``: the ``mntes-stream`` command.
"""

__version__ = "0.1.0"
