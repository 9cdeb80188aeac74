"""IceBoard (DfMux) packets straight from the boards, without SPT-3G's DAQ.

- :mod:`.packets`: the packet layout, byte for byte as spt3g's ``DfMuxCollector`` reads it.
- :mod:`.sender`: a synthetic board (its own process) for tests, ``bench dfmux`` and the lab recipe.
- :mod:`.bridge`: the ``dfmux-bridge`` service (spt3g's ``DfMuxCollector`` + ``DfMuxBuilder`` -> counts
  and housekeeping on zenoh).

Nothing here imports spt3g at import time; the bridge imports spt3g 1.0.2
itself, in a process that never imports so3g.
"""
