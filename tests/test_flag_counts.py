"""``core.flags.counts_by_flag``: the samples carrying each flag, checked against a count written out bit by bit."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mntes_stream.core import flags as fl


def _by_bit(flags: np.ndarray) -> dict[str, int]:
    """Each sample's bits read one by one in Python: the independent count."""
    out = dict.fromkeys(fl.NAMES.values(), 0)
    for value in flags.ravel().tolist():
        for bit, name in fl.NAMES.items():
            if value & bit:
                out[name] += 1
    return out


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), fraction=st.sampled_from([0.0, 0.001, 0.05, 0.249, 0.26, 0.6, 1.0]),
       rows=st.integers(0, 40), cols=st.integers(0, 30))
def test_counts_by_flag_equals_a_bit_by_bit_count_whether_few_or_most_samples_are_flagged(seed, fraction, rows,
                                                                                          cols):
    rng = np.random.default_rng(seed)
    flags = np.zeros((rows, cols), dtype=fl.FLAG_DTYPE)
    hit = rng.random(flags.shape) < fraction
    # single flags (each bit alone) and any mix of bits
    values = np.concatenate([np.array(list(fl.NAMES), dtype=np.uint16), rng.integers(1, 1 << 16, 16, dtype=np.uint16)])
    flags[hit] = rng.choice(values, size=int(hit.sum()))
    # a strided view (a chunk's columns of a block), as the pipeline passes
    block = np.zeros((rows, 3 * cols + 1), dtype=fl.FLAG_DTYPE)
    block[:, cols:2 * cols] = flags
    assert fl.counts_by_flag(flags) == _by_bit(flags)
    assert fl.counts_by_flag(block[:, cols:2 * cols]) == _by_bit(flags)
