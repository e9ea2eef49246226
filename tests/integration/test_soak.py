"""A shortened soak (issue 14, "Soak"; the full one is ``covnet bench soak``): a 3 000-scan
lockstep ``covnet up`` of the paper scenario and a 60 s real-time one, every process of the
network sampled five times a second; memory and descriptors stay flat after the warm-up, and the
latency windows are there for every scan."""

from __future__ import annotations

import pytest

from covnet.bench import soak as bench_soak

NODES = {"launcher", "manager", "world", "recorder", *(f"S{i}" for i in range(1, 9))}


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(600)
def test_short_soak_is_flat(tmp_path, paper_path):
    # sampled every 0.2 s: a quick host runs the 3 000 lockstep scans in 3.4 s, which at 0.5 s
    # left three samples after the warm-up, and two in a slow-suite run (it failed)
    rows = bench_soak.run(
        str(paper_path), 3000, 60.0, speed=10.0, interval_s=0.2, work=tmp_path, quiet=True
    )
    for phase, scans in (("lockstep", 3000), ("realtime", 600)):
        procs = [r for r in rows if r["phase"] == phase and r["row"] == "process"]
        assert {r["process"] for r in procs} == NODES, procs
        assert all(r["samples"] >= 3 for r in procs), procs
        grown = [
            f"{phase} {r['process']}: RSS {r['rss_start_kb']}->{r['rss_end_kb']} kB "
            f"({r['rss_growth_pct']:+.1f} %), fds {r['fd_start']}->{r['fd_end']}"
            for r in procs
            if not r["flat"]
        ]
        assert not grown, grown
        windows = [r for r in rows if r["phase"] == phase and r["row"] == "latency"]
        assert len(windows) == 10 and windows[-1]["last_scan"] == scans, windows
        assert all(0 < w["p50_ms"] <= w["p99_ms"] for w in windows), windows
        summary = next(r for r in rows if r["phase"] == phase and r["row"] == "summary")
        assert summary["scans"] == scans and summary["lost"] == 0, summary


def test_growth_is_measured_after_the_warm_up():
    """The first tenth of the run is warm-up; growth compares the medians of the first and the
    last tenth of what is left."""
    flat_then_jump = [(float(t), 100 if t < 10 else 200, 10) for t in range(100)]
    g = bench_soak.growth(flat_then_jump, 0.0, 99.0)
    assert g["samples"] == 90 and g["rss_start_kb"] == 200 and g["rss_growth_pct"] == 0.0
    rising = [(float(t), 1000 + t, 10 + t // 50) for t in range(100)]
    g = bench_soak.growth(rising, 0.0, 99.0)
    assert g["rss_start_kb"] == 1014 and g["rss_end_kb"] == 1095
    assert g["rss_growth_pct"] == pytest.approx(100 * 81 / 1014)
    assert g["fd_start"] == 10 and g["fd_end"] == 11 and g["fd_max"] == 11
    assert bench_soak.growth([], 0.0, 1.0)["rss_growth_pct"] is None


def test_latency_windows_cover_every_scan_in_order():
    # (episode, scan, command sent at k seconds, latency k ms, recorder lag 1 ms)
    lat = [(0, k, k * 10**9, k * 10**6, 10**6) for k in range(1, 101)]
    load = [(float(t), 1.0 if t <= 50 else 3.0) for t in range(0, 101, 5)]
    w = bench_soak.latency_windows(lat, 4, load)
    assert [(x["first_scan"], x["last_scan"], x["scans"]) for x in w] == [
        (1, 25, 25), (26, 50, 25), (51, 75, 25), (76, 100, 25),
    ]  # fmt: skip
    assert w[0]["max_ms"] == 25.0 and w[3]["p50_ms"] == pytest.approx(88.0)
    assert w[0]["recorder_lag_p99_ms"] == 1.0
    assert [x["load_1min"] for x in w] == [1.0, 1.0, 3.0, 3.0]
    assert bench_soak.latency_windows(lat, 2)[0]["load_1min"] is None
    assert bench_soak.latency_windows([], 10) == []
