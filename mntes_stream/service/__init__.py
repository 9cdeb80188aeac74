"""Long-running services: converter, recorder, replay (zenoh and MCAP at the edges)."""
