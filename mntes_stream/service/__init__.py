"""Long-running services and what runs them (zenoh and MCAP at the edges).

- ``base``: the service contract (:class:`~mntes_stream.service.base.Service`,
  heartbeat, stop flags);
- ``registry``: config table name -> service class;
- ``config``: config documents from files (layers, paths, ``config check/show``);
- ``supervise``: services as spawned processes (``up``, benchmarks);
- the services: ``converter`` (around ``pipeline``, the converter without
  zenoh, also used ``offline``), ``source``, ``simulator``, ``recorder``, ``replay``.
"""
