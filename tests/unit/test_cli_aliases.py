"""An option with an alias given twice is refused (exit 2, naming both): ``covnet compare
--runs 2 --seeds 3`` ran 3 seeds and ``covnet mc --trials 2 --seeds 3`` ran 3, without a word."""

from __future__ import annotations

import pytest

from covnet.cli.app import main
from tests.conftest import REPO

PAPER = str(REPO / "configs" / "paper.yaml")


@pytest.mark.parametrize(
    "argv,names",
    [
        (["compare", PAPER, "--runs", "2", "--seeds", "3"], "--runs and --seeds"),
        (["compare", PAPER, "--seeds", "2", "--seeds", "3"], "--seeds and --seeds"),
        (["mc", PAPER, "--trials", "2", "--seeds", "3"], "--trials and --seeds"),
    ],
)
def test_an_option_given_twice_is_refused(tmp_path, capsys, argv, names):
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exc:
        main([*argv, "--out", str(out)])
    assert exc.value.code == 2
    assert f"{names}: one option given twice" in capsys.readouterr().err
    assert not out.exists()


def test_bench_fusion_takes_the_repeat_given(monkeypatch, capsys):
    """``bench fusion --repeat 1`` timed 3 repeats (``max(repeat, 3)``), without a word."""
    from covnet.covariance_control import bench_fusion

    seen = []
    monkeypatch.setattr(
        bench_fusion, "run_bench", lambda sensors, repeat: seen.append(repeat) or []
    )
    assert main(["bench", "fusion", "--sensors", "4", "--repeat", "1", "--json"]) == 0
    assert seen == [1]
