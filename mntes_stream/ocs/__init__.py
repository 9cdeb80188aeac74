"""Housekeeping from OCS (the Simons Observatory control system), an edge package like ``g3/``.

A lab's bath thermometry usually reaches the world through OCS: Lakeshore
agents publish *feeds* over a crossbar WAMP router, and OCS's aggregator
writes them to HK G3 files. A field's full name is its feed address plus the
field, e.g. ``observatory.LS372.feeds.temperatures.Channel_06_T``.

- :mod:`mntes_stream.g3.ocs_hkfile`: OCS HK G3 files read with spt3g 1.0.2
  (``--hk FILE|DIR``); G3 work, hence in ``g3/``, which ``ocs/`` builds on.
- :mod:`mntes_stream.g3.ocs_hk`: OCS fields mapped to the project's sensors,
  readings as :class:`~mntes_stream.io.messages.HousekeepingChunk` messages.
- :mod:`.bridge`: the ``ocs-bridge`` service (a WAMP client of the router,
  publishing the configured fields on zenoh; optional extra ``ocs``).
"""
