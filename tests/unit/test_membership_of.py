"""``run.json``'s ``membership`` of a run rebuilt from its recording (the manager killed): the
counts from the rebuilt failure events equal what the manager's own loop counts for the same
run (the rebuilt ``run.json`` had no ``membership`` at all)."""

from __future__ import annotations

import json
from types import SimpleNamespace

from hypothesis import given, settings
from hypothesis import strategies as st

from covnet.processes.runtime_stats import NetStats
from covnet.processes.up import membership_of, settle
from manager.loop import Loop

SENSORS = ("S1", "S2", "S3", "S4")


class _Members:
    """The failed set the manager's membership view gives at each call, scripted."""

    def __init__(self) -> None:
        self.now: frozenset[str] = frozenset()

    def failed(self, _now_ns: int) -> frozenset[str]:
        return self.now

    def down_since_ns(self, _sid: str) -> int:
        return 7


def _manager_loop() -> Loop:
    """The manager's :class:`Loop`, only as far as ``membership_changes`` reads it."""
    loop = object.__new__(Loop)
    loop.members = _Members()  # type: ignore[assignment]
    loop.stats = NetStats()
    loop.forged_done = False
    loop.clock = SimpleNamespace(now_ns=lambda: 0)  # type: ignore[assignment]
    loop._counted_failed = frozenset()
    loop.poll_membership = lambda: None  # type: ignore[method-assign]
    return loop


def _run(episodes: list[list[frozenset[str]]]) -> tuple[dict, dict]:
    """The manager's per-episode event logs (without their detection times, as summary.json
    holds them) and its run-wide membership counts, for the failed sets of every scan."""
    loop, logs = _manager_loop(), {}
    for e, scans in enumerate(episodes):
        previous: frozenset[str] = frozenset()
        log = logs[f"m{e}"] = []
        for k, now in enumerate(scans, start=1):
            loop.members.now = now
            previous, events = loop.membership_changes(k, previous)
            log += [{x: v for x, v in ev.items() if x != "detected_ns"} for ev in events]
    return logs, loop.stats.membership_counts()


failed_sets = st.frozensets(st.sampled_from(SENSORS), max_size=3)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.lists(failed_sets, min_size=1, max_size=6), min_size=1, max_size=4))
def test_counts_from_the_events_equal_the_managers(episodes):
    logs, counted = _run(episodes)
    done = {m: len(scans) for m, scans in zip(logs, episodes, strict=True)}
    assert membership_of(logs, done) == counted
    if len(episodes) == 1:  # the kinds that log one list
        assert membership_of(logs["m0"]) == counted


def test_a_node_back_between_two_episodes_is_a_rejoin_and_an_episode_not_run_is_nothing():
    down, up = frozenset({"S2"}), frozenset()
    logs, counted = _run([[up, down], [up, up]])
    assert counted == {"S2": {"failed": 1, "rejoined": 1}}  # the second episode logs nothing
    assert logs["m1"] == []
    assert membership_of(logs, {"m0": 2, "m1": 2}) == counted
    # an episode the run never reached (no scan done) counts no rejoin
    assert membership_of({"m0": logs["m0"], "m1": []}, {"m0": 2, "m1": 0}) == {
        "S2": {"failed": 1, "rejoined": 0}
    }


def test_a_rebuilt_run_json_gets_the_membership(tmp_path):
    """settle() after the manager died: run.json is rebuilt from the recording by the kind's
    replay; the membership the manager would have written is now there."""
    logs, counted = _run([[frozenset(), frozenset({"S3"})], [frozenset({"S3"}), frozenset()]])
    (tmp_path / "recording.mcap").write_bytes(b"x")

    class Kind:
        @staticmethod
        def episodes(_sc):
            return list(logs)

        @staticmethod
        def rebuild(sc, run_id, episodes, recording, out, info):
            (out / "run.json").write_text(json.dumps({"run_id": run_id, "mode": "network"}))
            done = {m: 2 for m in episodes}
            summary = {"failures": logs, "scans_completed": done}
            (out / "summary.json").write_text(json.dumps(summary))
            return SimpleNamespace(notes=[])

    said = settle(Kind, None, tmp_path, {"run_id": "r1"}, "failed", "the manager died")
    assert said.startswith("rebuilt"), said
    info = json.loads((tmp_path / "run.json").read_text())
    assert info["membership"] == counted == {"S3": {"failed": 1, "rejoined": 1}}


def test_a_rebuilt_peer_run_has_no_membership_as_the_monitor_writes_none(tmp_path):
    """Peer mode has no fusion centre to count failures (README: `membership` stays empty);
    the rebuild counted the majority's failures as a centre's."""
    (tmp_path / "recording.mcap").write_bytes(b"x")

    class Kind:
        @staticmethod
        def episodes(_sc):
            return ["spectral"]

        @staticmethod
        def rebuild(sc, run_id, episodes, recording, out, info):
            (out / "run.json").write_text(json.dumps({"run_id": run_id, "mode": "network"}))
            fails = {"spectral": [{"sensor": "S3", "scan": 24, "event": "failed"}]}
            summary = {"failures": fails, "scans_completed": {"spectral": 30}, "peer": {}}
            (out / "summary.json").write_text(json.dumps(summary))
            return SimpleNamespace(notes=[])

    settle(Kind, None, tmp_path, {"run_id": "r1"}, "failed", "the monitor died")
    assert json.loads((tmp_path / "run.json").read_text())["membership"] == {}
