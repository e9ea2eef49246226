"""The manager's batched collect against its per-message one, bit for bit:

- the engine's verdicts on a scan's measurements computed together
  (:meth:`ScanEngine.verdicts`) are :meth:`ScanEngine.verdict` of each, forged (outside the
  gate), unusable (asymmetric or not positive definite ``R``, ``R₀₀ R₁₁ − R₀₁²`` at the edge)
  and late messages among them;
- :meth:`manager.loop.Loop._take_many` of a batch of samples (good, duplicated, forged,
  malformed, from the wrong key, of another scan, late, not enabled, badly numbered) leaves
  the loop's counts, rejections, latencies and taken messages exactly as :meth:`Loop._take` of
  each sample in turn."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from covnet.clock import WallClock
from covnet.config import NetworkSpec
from covnet.covariance_control.engine import ScanEngine
from covnet.wire import messages as msg
from covnet.wire.bus import InMemoryBus, Sample
from manager.covariance import CovarianceLogic
from manager.loop import MIN_BATCH, MIN_VERDICTS, Loop

pytestmark = pytest.mark.usefixtures("room_in_the_names_cache")


def _message(
    sid: str, scan: int, z: np.ndarray, R: np.ndarray, seq: int, episode: int = 0
) -> msg.Measurement:
    return msg.Measurement(
        sensor_id=sid, scan=scan, t=0.1 * scan, z=z, R=R, t_sent_ns=1000 + seq, episode=episode,
        seq=seq,
    )  # fmt: skip


def _scan_messages(engine: ScanEngine, plan, rng: np.random.Generator) -> list[msg.Measurement]:
    """Scan ``plan.k``'s messages of every sensor, some forged or unusable, a few late."""
    model, ids = engine.model, engine.ids
    pred = plan.detail[0]
    hx = model.H @ pred.x
    out = []
    for j, sid in enumerate(ids):
        R = np.array(model.R[j])
        z = (hx + rng.normal(size=2) * np.sqrt(np.diag(R)))[None, :]
        kind = rng.integers(0, 9)
        if kind == 0:  # forged: kilometres away
            z = z + rng.choice([-1, 1]) * 10.0 ** rng.uniform(2, 5)
        elif kind == 1:  # asymmetric R
            R = R.copy()
            R[0, 1] += 1e-3
        elif kind == 2:  # not positive definite
            R = np.array([[1.0, 2.0], [2.0, 1.0]])
        elif kind == 3:  # R₀₀ R₁₁ = R₀₁² (singular), and one ulp either side
            a = float(rng.uniform(0.5, 3))
            b = float(rng.uniform(0.5, 3))
            c = float(np.sqrt(a * b))
            c = [c, np.nextafter(c, 0), np.nextafter(c, 10)][int(rng.integers(0, 3))]
            R = np.array([[a, c], [c, b]])
        elif kind == 4:  # on the gate's edge: far out along one axis
            z = z + np.array([[rng.uniform(0, 80) * np.sqrt(R[0, 0]), 0.0]])
        elif kind == 5:  # late: an earlier scan (content only)
            out.append(_message(sid, max(plan.k - 1, 0), z, R, 1))
            continue
        out.append(_message(sid, plan.k, z, R, 2))
    return out


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), k=st.integers(1, 40))
def test_engine_verdicts_together_equal_one_by_one(paper, seed, k):
    rng = np.random.default_rng(seed)
    engine = ScanEngine(paper, ["logdet"])
    engine.start_episode(0)
    plan = None
    for kk in range(1, k + 1):  # the filter's real state at scan k
        plan = engine.decide(kk)
        engine.ahead(plan)
        if kk < k:
            got = {m.sensor_id: m for m in _scan_messages(engine, plan, rng) if m.scan == kk}
            got = {s: m for s, m in got.items() if engine.verdict(m) is None and s in plan.enabled}
            engine.fuse(plan, got)
    ms = _scan_messages(engine, plan, rng)
    one_by_one = [engine.verdict(m) for m in ms]
    assert engine.verdicts(ms) == one_by_one
    assert engine.verdicts(ms[::-1]) == one_by_one[::-1]
    assert engine.verdicts([]) == []


def test_engine_verdicts_see_every_reason(paper):
    """The generator above reaches all three verdicts (so the comparison means something)."""
    rng = np.random.default_rng(3)
    engine = ScanEngine(paper, ["logdet"])
    engine.start_episode(0)
    plan = engine.decide(1)
    seen = set()
    for _ in range(20):
        seen.update(engine.verdicts(_scan_messages(engine, plan, rng)))
    assert seen == {None, "bad_measurement", "outside_gate"}


# --------------------------------------------------------------------------------------------
# the loop
# --------------------------------------------------------------------------------------------


def _loop(paper) -> tuple[Loop, CovarianceLogic]:
    loop = Loop(NetworkSpec(), paper.sensor_ids, InMemoryBus(), "bt", WallClock())
    logic = CovarianceLogic(paper, loop)
    logic.start_episode(0)
    return loop, logic


def _batch(paper, plan, engine, rng: np.random.Generator) -> list[Sample]:
    ids = paper.sensor_ids
    good = _scan_messages(engine, plan, rng)
    key = lambda sid: msg.measurement_key("bt", sid)  # noqa: E731
    samples = [Sample(key(m.sensor_id), msg.encode(m), 5000 + i) for i, m in enumerate(good)]

    def enc(sid: str, scan: int, like: msg.Measurement, seq: int, episode: int = 0) -> bytes:
        return msg.encode(_message(sid, scan, like.z, like.R, seq, episode))

    k = plan.k
    extra = [
        Sample(key(ids[0]), samples[1].payload, 1),  # another sensor's on my key
        Sample(key(ids[2]), b"\x93\x01\x02", 2),  # not a map
        Sample(key(ids[2]), samples[2].payload[:-3], 3),  # truncated
        Sample("covnet/bt/sensor/zz!/meas", samples[3].payload, 4),  # bad key
        Sample(key("stranger"), enc("stranger", k, good[0], 9), 5),  # not a sensor of ours
        Sample(samples[4].key, samples[4].payload, 6),  # the same again: duplicate seq
        Sample(samples[5].key, enc(ids[5], k, good[5], 7), 7),  # a second one: duplicate
        Sample(samples[6].key, enc(ids[6], k + 1, good[6], 8), 8),  # wrong scan
        Sample(samples[7].key, enc(ids[7], k, good[7], 0), 9),  # seq 0: bad_seq
        Sample(samples[1].key, enc(ids[1], k, good[1], 11, 1), 10),  # another episode
    ]  # fmt: skip
    batch = samples + extra
    order = rng.permutation(len(batch))
    return [batch[i] for i in order]


def _state(loop: Loop, got: dict, waiting: set) -> dict:
    st_ = loop.stats
    return {
        "recv_msgs": dict(st_.recv_msgs),
        "recv_bytes": dict(st_.recv_bytes),
        "rejected": dict(st_.rejected),
        "rejected_by_key": {k: dict(v) for k, v in st_.rejected_by_key.items()},
        "outcome": {k: dict(v) for k, v in st_.outcome.items()},
        "late": (st_.late, st_.late_refiltered, st_.late_dropped, st_.unsolicited),
        "meas_latency_ns": list(st_.meas_latency_ns),
        "seq": {k: (v.high, v.arrived, bytes(v.seen)) for k, v in st_.seq.items()},
        "got": [(s, msg.encode(m)) for s, m in got.items()],
        "waiting": sorted(waiting),
        "heard": sorted(loop.members.last_heartbeat_ns),
    }


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("k", [1, 2, 9])
def test_take_many_equals_take_one_by_one(paper, seed, k):
    rng = np.random.default_rng(seed)
    runs = []
    for together in (False, True):
        loop, logic = _loop(paper)
        for kk in range(1, k + 1):  # the same plans in both loops
            decision = logic.decide(0, kk, frozenset())
            logic.ahead(0, kk)
            if kk < k:
                logic.fuse(0, kk, {})
        batch = _batch(paper, logic.plan, logic.engine, np.random.default_rng(seed))
        assert len(batch) >= max(MIN_BATCH, MIN_VERDICTS)  # the batch path, verdicts too
        waiting, got = set(decision.enabled), {}
        if together:
            loop._take_many(
                batch, 0, k, waiting, got, logic.usable, msg.Measurement, logic.usable_many
            )
        else:
            for s in batch:
                loop._take(s, 0, k, waiting, got, logic.usable, msg.Measurement)
        runs.append(_state(loop, got, waiting))
    assert runs[1] == runs[0]
    assert runs[0]["got"] and runs[0]["rejected"]  # some taken, some refused
    assert rng is not None


def test_take_many_takes_the_batch_path(paper, monkeypatch):
    """A clean batch is decoded together: per-message decoding is not called for it."""
    loop, logic = _loop(paper)
    decision = logic.decide(0, 1, frozenset())
    logic.ahead(0, 1)
    engine, plan = logic.engine, logic.plan
    pred = plan.detail[0]
    hx = engine.model.H @ pred.x
    batch = [
        Sample(
            msg.measurement_key("bt", sid),
            msg.encode(_message(sid, 1, hx[None, :], np.array(engine.model.R[j]), 1)),
            1,
        )
        for j, sid in enumerate(paper.sensor_ids)
    ]
    calls = []
    monkeypatch.setattr(loop, "_take", lambda *a, **kw: calls.append(a))
    waiting, got = set(decision.enabled), {}
    loop._take_many(batch, 0, 1, waiting, got, logic.usable, msg.Measurement, logic.usable_many)
    assert calls == [] and sorted(got) == sorted(decision.enabled) and not waiting
