"""core.sequence: the one sequence tracker (converter, recorder, feeds, monitor) counts honestly, in bounded memory."""

from __future__ import annotations

import random

from hypothesis import given, settings
from hypothesis import strategies as st

from mntes_stream.core.sequence import _MAX_RANGES, MAX_RECENT, StreamSequence, Verdict

P = 1_000_000  # ns between chunks


def _feed(order, period=P, t0=0):
    s = StreamSequence()
    verdicts = [s.observe(n, t0 + n * period) for n in order]
    return s, verdicts


@settings(max_examples=60, deadline=None)
@given(n=st.integers(10, 400), swaps=st.integers(0, 50), seed=st.integers(0, 10**6))
def test_reordering_without_loss_ends_with_nothing_lost(n, swaps, seed):
    order = list(range(n))
    rng = random.Random(seed)
    for _ in range(swaps):  # local reordering, as a network does it
        i = rng.randrange(1, n)
        order[i - 1], order[i] = order[i], order[i - 1]
    s, verdicts = _feed(order)
    assert s.lost == 0 and s.resets == 0 and s.duplicated == 0
    assert s.out_of_order == verdicts.count("late")


def test_a_real_gap_is_lost_and_late_arrivals_take_it_back():
    order = [0, 1, 2] + list(range(12, 20)) + [5, 6]
    s, verdicts = _feed(order)
    assert (s.lost, s.out_of_order, s.resets) == (9 - 2, 2, 0)
    assert verdicts[-2:] == ["late", "late"]


def test_verdicts_are_typed_and_read_as_their_names():
    s, verdicts = _feed([0, 1, 3, 2, 2])
    assert verdicts == [Verdict.NEW, Verdict.NEW, Verdict.NEW, Verdict.LATE, Verdict.DUPLICATE]
    assert all(type(v) is Verdict for v in verdicts) and [str(v) for v in verdicts[-2:]] == ["late", "duplicate"]
    assert s.newest_t_ns == 3 * P
    assert s.observe(100_000, 40 * P) is Verdict.RESET


def test_a_forged_number_is_a_reset_not_thousands_lost():
    s, _ = _feed(range(10))
    assert s.observe(4000, t_first_ns=10 * P) == "reset"  # 3,990 chunks cannot fit in one period
    assert s.lost == 0 and s.resets == 1
    assert s.observe(4001, t_first_ns=11 * P) == "new" and s.lost == 0


def test_a_source_restart_after_many_chunks_is_a_reset_not_out_of_order():
    for run in (300, 1000, 4000):  # between the duplicate window (256) and the jump limit (4096)
        s, _ = _feed(range(run))
        assert s.observe(0, t_first_ns=(run + 5) * P) == "reset", run  # old number, newer samples
        assert s.out_of_order == 0 and s.resets == 1
        assert [s.observe(k, (run + 5 + k) * P) for k in (1, 2)] == ["new", "new"]


def test_duplicates_are_dropped_and_a_recent_number_with_other_samples_restarts():
    s, _ = _feed(range(5))
    assert s.observe(3, 3 * P) == "duplicate" and s.duplicated == 1
    assert s.observe(3, 99 * P) == "reset"


def test_memory_is_bounded_whatever_numbers_a_peer_sends():
    s = StreamSequence()
    rng = random.Random(1)
    t = 0
    for _ in range(50_000):
        t += P
        s.observe(rng.randrange(0, 1 << 40), t)
    assert len(s._missing) <= _MAX_RANGES and len(s._recent) <= MAX_RECENT and len(s._recent_t) <= MAX_RECENT
    # Every jump of more than the time allows was a reset: nothing counted lost.
    assert s.lost == 0 and s.resets >= 49_000
