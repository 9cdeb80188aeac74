"""The recorder's MCAP message path (``_LeanWriter``) against mcap's public ``Writer``, same process, alternated.

    PYTHONPATH=. python benchmarks/recording_public_writer.py [bench recording options, e.g. --compression none]

Runs ``mntes-stream bench recording --repeat 3`` twice per writer in turn (lean, public, lean, public), swapping
the class ``McapFileWriter`` instantiates, and prints each run's median CPU s per M counts samples; figures in
``benchmarks/recording.json`` ``lean_writer_vs_public_api`` (why pyproject pins mcap to 1.6.x).
"""

import argparse
import json
import sys

import mcap.writer

import mntes_stream.io.mcap.writer as w
from mntes_stream.bench import recording

lean = w._LeanWriter
p = argparse.ArgumentParser()
recording.add_arguments(p)
args = p.parse_args(["--repeat", "3"] + sys.argv[1:])
res = {}
for rnd in range(2):
    for name, cls in (("lean", lean), ("public", mcap.writer.Writer)):
        w._LeanWriter = cls
        r = recording.run(args)
        res.setdefault(name, []).append(r["cpu_s_per_msamples"])
        print(rnd, name, r["cpu_s_per_msamples"], r["compression"], r["chunk_kb"], flush=True)
print(json.dumps(res))
