"""``covnet bench soak``'s growth: a leak is growth after the warm-up; the result columns'
spill files, opened once at their first full block, are not."""

from __future__ import annotations

from covnet.bench.soak import FLAT_PCT, growth, phase_warmup
from covnet.runs.columns import BLOCK


def _fds(scans: int, step_at: int, step: int, leak_every: int = 0) -> list[tuple[float, int, int]]:
    """One sample a scan (time = scan number): 29 descriptors, ``step`` more from scan
    ``step_at`` on, and one more every ``leak_every`` scans (a leak) when given."""
    out = []
    for k in range(1, scans + 1):
        n = 29 + (step if k > step_at else 0) + (k // leak_every if leak_every else 0)
        out.append((float(k), 60_000, n))
    return out


def test_the_columns_first_spill_is_in_the_warm_up():
    scans = 3000  # the slow soak test's lockstep phase: the spill at a third of the run
    samples = _fds(scans, BLOCK + 1, 10)
    assert growth(samples, 0.0, scans, 0.1)["fd_growth_pct"] > FLAT_PCT  # the old warm-up
    assert growth(samples, 0.0, scans, phase_warmup(0.1, scans))["fd_growth_pct"] == 0.0


def test_a_leak_is_still_growth():
    scans = 3000
    samples = _fds(scans, BLOCK + 1, 10, leak_every=100)  # +30 descriptors over the run
    assert growth(samples, 0.0, scans, phase_warmup(0.1, scans))["fd_growth_pct"] > FLAT_PCT


def test_the_warm_up_is_the_given_one_where_no_column_spills_or_it_is_longer():
    assert phase_warmup(0.1, BLOCK) == 0.1
    assert 0.1 <= phase_warmup(0.1, 20_000) < 0.11  # the default soak: about its 10 %
    assert phase_warmup(0.1, 3000) == (BLOCK + 1) / 3000 + 0.05
    assert phase_warmup(0.1, BLOCK + 2) == 0.5


def test_the_warm_up_ends_at_the_first_status_past_the_block():
    """Under load the pace is uneven: the run's own ``[status]`` lines say when the block was
    passed (the first one past scan ``BLOCK``; the step came before it)."""
    lines = [
        (1.0, "[manager] READY"),
        (2.0, "[status] spectral: 1/3000 8/8 on"),
        (6.0, f"[status] spectral: scan {BLOCK - 1}/3000  enabled S1"),
        (7.0, f"[status] spectral: {BLOCK + 300}/3000 5/8 on  trP 15/16"),
    ]
    assert phase_warmup(0.1, 3000, lines, 1.0, 11.0) == 0.6  # (7 - 1) / (11 - 1)
    assert phase_warmup(0.1, 3000, lines[:3], 1.0, 11.0) == (BLOCK + 1) / 3000 + 0.05
    assert phase_warmup(0.1, 3000, [(10.9, lines[-1][1])], 1.0, 11.0) == 0.9  # at most


def test_a_phase_too_short_to_sample_is_reported_not_a_traceback(capsys):
    """``covnet bench soak --scans 300``: a lockstep phase of 0.6 s has no sample after its
    warm-up at the default 2 s interval.  Its rows had other keys (``rss_start`` for
    ``rss_start_kb``) and the table ended in a KeyError; such a process is now shown as not
    measured (``-``), with a note, and is not counted flat."""
    from covnet.bench.soak import _print_table

    empty = growth([], 0.0, 0.6, 0.1)
    full = growth([(0.3, 60_000, 29), (0.5, 60_000, 29)], 0.0, 0.6, 0.1)
    assert set(empty) == set(full) and empty["samples"] == 0
    assert all(v is None for k, v in empty.items() if k != "samples")
    rows = [
        {"phase": "lockstep", "row": "summary", "scans": 300, "loop_s": 0.6, "scans_per_s": 500.0,
         "scan_p50_ms": 1.8, "scan_p99_ms": 2.9, "late": 0, "lost": 0},  # fmt: skip
        {"phase": "lockstep", "row": "process", "process": "manager", "pid": 1, **empty,
         "flat": None},  # fmt: skip
    ]
    _print_table(rows)
    out = capsys.readouterr().out
    assert "manager" in out and "not measured" in out and "--interval" in out


def test_one_sample_is_not_measured():
    """One sample after the warm-up was its own start and end: "+0.0 %, flat", exit 0, for a
    leak check that measured nothing."""
    one = growth([(0.5, 60_000, 29)], 0.0, 0.6, 0.1)
    assert one["samples"] == 1 and one["rss_growth_pct"] is None and one["fd_growth_pct"] is None


def test_the_soak_runs_the_metric_asked_for(tmp_path, paper_path):
    """A config without allocation.metrics kept the default three, whatever --metric said
    (three episodes, the first one timed); a name no metric has was taken silently."""
    import pytest
    import yaml

    from covnet.bench.soak import _soak_config
    from covnet.errors import UsageError
    from covnet.kinds import load

    data = yaml.safe_load(paper_path.read_text())
    del data["allocation"]["metrics"]
    src = tmp_path / "nometrics.yaml"
    src.write_text(yaml.safe_dump(data))
    _, cfg = load(str(_soak_config(str(src), tmp_path, 30, "kl")))
    assert list(cfg.allocation.metrics) == ["kl"]
    _, cfg = load(str(_soak_config(str(src), tmp_path, 30, None)))
    assert list(cfg.allocation.metrics) == ["spectral"]  # the first of the default list
    with pytest.raises(UsageError, match="--metric: unknown metric 'bogus'"):
        _soak_config(str(src), tmp_path, 30, "bogus")
