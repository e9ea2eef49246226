"""What became of each sensor's messages (covnet.processes.runtime_stats): ``sent = on_time + late +
rejected + lost``, where lost means sent and never arrived (a gap in ``seq``, or beyond the
last one received when the sensor's own count says so), never "late"."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from covnet.processes.runtime_stats import SEQ_AHEAD, NetStats, SeqCount


def test_gaps_are_lost_duplicates_refused():
    c = SeqCount()
    for s in (1, 2, 4, 7):
        assert c.add(s) is None
    assert c.add(4) == "duplicate"
    assert (c.sent, c.arrived, c.lost) == (7, 4, 3)


def test_the_sensors_own_count_covers_the_last_ones():
    c = SeqCount()
    c.add(1)
    c.add(2)
    c.report(5)  # it sent 3 more that never came
    assert (c.sent, c.lost) == (5, 3)
    c.report(4)  # an older heartbeat changes nothing
    assert c.sent == 5


def test_a_forged_number_far_ahead_is_refused_and_costs_no_memory():
    c = SeqCount()
    c.add(1)
    assert c.add(SEQ_AHEAD + 10) == "bad_seq"
    assert c.add(0) == "bad_seq"
    assert len(c.seen) <= 1 and c.sent == 1
    c.report(10**12)
    assert c.sent == 1


def test_a_restarted_sensor_counts_again_from_one():
    c = SeqCount()
    for s in (1, 2, 3):
        c.add(s, (0, s))
    c.report(4)  # one lost before it died
    assert c.add(1, (0, 9)) is None  # the new process, at a later scan
    c.add(3, (0, 11))
    assert (c.sent, c.lost) == (4 + 3, 1 + 1)


def test_a_copy_of_seq_one_is_a_duplicate_not_a_restart():
    """One replayed seq-1 message (scan 1) mid-run was taken for a restarted process: the
    stretch so far folded away and the real next seq opened a gap, 51 to 379 messages
    "lost" of a sensor that lost none."""
    c = SeqCount()
    for s in range(1, 988):
        assert c.add(s, (0, s)) is None
    assert c.add(1, (0, 1)) == "duplicate"  # the copy: the same scan as the first seq 1
    assert c.add(1, None) == "duplicate"  # (no scan given: never a restart)
    assert c.add(988, (0, 988)) is None
    assert (c.sent, c.arrived, c.lost) == (988, 988, 0)


@given(
    sent=st.integers(1, 300),
    picks=st.lists(st.integers(1, 300), max_size=400),
    report=st.booleans(),
)
def test_lost_is_sent_minus_distinct_arrivals(sent, picks, report):
    c = SeqCount()
    arrived = [p for p in picks if p <= sent and p != 1]  # no restart in this property
    for p in arrived:
        c.add(p)
    if report:
        c.report(sent)
    distinct = set(arrived)
    expect_sent = sent if report else max(distinct, default=0)
    assert c.sent == expect_sent
    assert c.arrived == len(distinct)
    assert c.lost == expect_sent - len(distinct)


def test_network_json_per_sensor_block():
    ns = NetStats()
    for seq in (1, 2, 3, 5):
        assert ns.arrived("S1", seq) is None
    ns.outcome["S1"].update(on_time=2, late=1, late_refiltered=1, rejected=1)
    ns.reported("S1", 6)
    d = ns.as_dict()
    s1 = d["sensors"]["S1"]
    assert s1 == {
        "sent": 6,
        "on_time": 2,
        "late": 1,
        "late_refiltered": 1,
        "late_dropped": 0,
        "rejected": 1,
        "lost": 2,
    }
    assert s1["sent"] == s1["on_time"] + s1["late"] + s1["rejected"] + s1["lost"]
    assert d["lost"] == 2
    # an unnumbered message is not a sensor's (each numbers its own): refused, not counted
    assert ns.arrived("S1", None) == "missing_seq"
    assert ns.as_dict()["sensors"]["S1"] == s1
