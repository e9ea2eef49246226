"""Results the refactors may not change: every shipped config through the CLI, hashed
(``tests/golden/golden.py``), against ``tests/golden/hashes.json``, recorded on the code before
the architecture change of issue 13.  ``covnet run`` and ``covnet up`` of the paper scenario,
the decentralized and slow-link variants, mobile and passive, their Monte Carlo, ``compare``
and a small ``sweep``: byte for byte (wall-clock fields, which issue 13 moved to ``run.json``,
left out of the old files' hashes)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

GOLDEN = Path(__file__).resolve().parents[1] / "golden"
sys.path.insert(0, str(GOLDEN))

import golden  # noqa: E402

EXPECTED = json.loads((GOLDEN / "hashes.json").read_text())
OTHER_HOSTS = json.loads((GOLDEN / "hashes_other_hosts.json").read_text())
"""Per case, the hashes of the code before the change on another host class (its ``_note``
says which and why): a case passes with either set."""


def accepted(case: str) -> list[dict[str, str]]:
    return [EXPECTED[case], *OTHER_HOSTS.get(case, [])]


_RUNS: dict[str, tuple[Path, dict[str, str]]] = {}
"""Each in-process case run once per session: ``case -> (its work directory, its hashes)``
(the wall-clock test below reads the same run's files)."""


def _run_once(case: str, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, str]]:
    if case not in _RUNS:
        work = tmp_path_factory.mktemp(f"golden-{case}")
        argv, files = golden.CASES[case]
        _RUNS[case] = (work, golden.run_case(case, argv, files, work))
    return _RUNS[case]


@pytest.mark.parametrize("case", sorted(golden.CASES))
def test_in_process_results_unchanged(case, tmp_path_factory):
    assert _run_once(case, tmp_path_factory)[1] in accepted(case)


@pytest.mark.integration
@pytest.mark.timeout(240)
@pytest.mark.parametrize("case", sorted(golden.UP_CASES))
def test_network_results_unchanged(case, tmp_path):
    argv, files = golden.UP_CASES[case]
    assert golden.run_case(case, argv, files, tmp_path) in accepted(case)


def _keys(obj: object) -> set[str]:
    if isinstance(obj, dict):
        return set(obj) | {k for v in obj.values() for k in _keys(v)}
    if isinstance(obj, list):
        return {k for v in obj for k in _keys(v)}
    return set()


@pytest.mark.parametrize(
    "case,result,info_key",
    [
        ("run-mobile", "summary.json", "decision_time_s"),
        ("run-passive", "association.json", "association_time_s"),
        ("mc-mobile", "montecarlo.json", "decision_time_median_s"),
    ],
)
def test_wall_clock_facts_are_not_in_the_results(case, result, info_key, tmp_path_factory):
    """Issue 13, defect 4: a mobile summary (a passive association, a mobile Monte Carlo) holds
    only what the config and seeds determine; the decision (association) times are in
    run.json."""
    work, _ = _run_once(case, tmp_path_factory)
    doc = json.loads((work / case / result).read_text())
    assert not _keys(doc) & golden.WALL_CLOCK_KEYS, _keys(doc) & golden.WALL_CLOCK_KEYS
    assert info_key in json.loads((work / case / "run.json").read_text())
