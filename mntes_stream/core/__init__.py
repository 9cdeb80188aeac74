"""Pure computation: physics, tables, conversion, alignment. No I/O here.

``tests/test_layering.py`` enforces that nothing under ``core`` imports the
edges (zenoh, mcap, msgpack, the CLI) or does file I/O.
"""
