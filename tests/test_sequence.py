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


def _ranges_of(numbers) -> list[tuple[int, int]]:
    """[lo, hi) runs of a set of numbers, computed here without SeqRanges."""
    out: list[list[int]] = []
    for n in sorted(set(numbers)):
        if out and n == out[-1][1]:
            out[-1][1] += 1
        else:
            out.append([n, n + 1])
    return [(a, b) for a, b in out]


@settings(max_examples=80, deadline=None)
@given(a=st.lists(st.integers(0, 300), max_size=300), b=st.lists(st.integers(0, 300), max_size=300),
       below=st.one_of(st.none(), st.integers(0, 320)))
def test_seq_ranges_hold_exactly_the_numbers_added(a, b, below):
    from mntes_stream.core.sequence import SeqRanges

    ra, rb = SeqRanges(), SeqRanges()
    assert [ra.add(n) for n in a] == [n not in a[:i] for i, n in enumerate(a)]  # False: there already
    for n in b:
        rb.add(n)
    assert ra.ranges() == _ranges_of(a) and ra.count == len(set(a)) and ra.untracked == 0
    assert ra.newest == (max(a) if a else None)
    want = {n for n in set(a) - set(b) if below is None or n < below}
    assert ra.minus(rb, below) == _ranges_of(want)
    assert ra.union(rb).ranges() == _ranges_of(set(a) | set(b))
    again = SeqRanges.from_list(ra.to_list()[::-1])  # read back in any order
    assert again.ranges() == ra.ranges() and again.count == ra.count


def test_seq_ranges_are_bounded_and_say_what_they_could_not_place():
    from mntes_stream.core.sequence import SeqRanges, format_ranges

    r = SeqRanges(max_ranges=4)
    for n in range(0, 40, 2):  # every other number: a range each
        r.add(n)
    assert len(r.ranges()) == 4 and r.count == 4 and r.untracked == 16
    r.add(1)  # joins two kept ranges: still placed
    assert r.ranges()[0] == (0, 3) and r.count == 5
    assert format_ranges([(0, 98)]) == "seq 0-97"
    assert format_ranges([(0, 1), (5, 9), (12, 13)], most=2) == "seq 0, 5-8 and 1 more range"


@settings(max_examples=60, deadline=None)
@given(n=st.integers(20, 200), offset=st.integers(1, 3000), shift_ns=st.integers(1, P - 1), seed=st.integers(0, 10**6))
def test_two_publishers_side_by_side_are_numbered_apart_and_lose_nothing(n, offset, shift_ns, seed):
    """Two sources on one key, each numbering its own chunks (one started ``offset`` chunks later), interleaved
    as a network does: booked as one stream they lose chunks at every switch; apart, none."""
    from mntes_stream.core.sequence import PublisherSequences

    rng = random.Random(seed)
    a = [(k + offset, k * P, "a") for k in range(n)]
    b = [(k, k * P + shift_ns, "b") for k in range(n)]
    order = sorted(a + b, key=lambda c: c[1] + rng.randrange(P // 2))
    s = PublisherSequences()
    verdicts = [s.observe(*c) for c in order]
    assert s.conflict and s.publishers == 2
    assert s.lost == 0 and verdicts.count(Verdict.DUPLICATE) == 0


def test_one_publisher_after_another_is_a_restart_as_before_and_copies_are_duplicates():
    from mntes_stream.core.sequence import PublisherSequences

    # A source restarted (a new zenoh session) that numbers on: what it did not send meanwhile is lost, as for
    # one publisher; no conflict (the first never comes back).
    s, one = PublisherSequences(), StreamSequence()
    for n, src in [(k, "a") for k in range(10)] + [(k, "b") for k in range(15, 30)]:
        assert s.observe(n, n * P, src) == one.observe(n, n * P)
    assert not s.conflict and s.lost == one.lost == 5
    # ... or starts over: a reset, nothing lost.
    s = PublisherSequences()
    verdicts = [s.observe(n, (100 + n) * P if src == "b" else n * P, src)
                for n, src in [(k, "a") for k in range(5000, 5010)] + [(k, "b") for k in range(5)]]
    assert verdicts[10] is Verdict.RESET and not s.conflict and s.lost == 0
    # Two bridges sending the same chunks: each copy after the first is a duplicate, nothing lost.
    s = PublisherSequences()
    verdicts = [s.observe(k, k * P, src) for k in range(50) for src in ("a", "b")]
    assert s.lost == 0 and verdicts.count(Verdict.DUPLICATE) == 50 and s.duplicated == 50
