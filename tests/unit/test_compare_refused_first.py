"""``covnet compare --modes`` refuses a mode whose config is invalid before it touches
``--out``: a custom peer graph without edges was refused only once the batch's directory had
been made (a new one left holding ``batch.json``) or, with ``--force``, emptied (an earlier
batch's results gone).  ``--graph`` with no peer mode among ``--modes`` was ignored."""

from __future__ import annotations

import pytest

from covnet.cli.app import main
from tests.conftest import REPO

PAPER = str(REPO / "configs" / "paper.yaml")


def _files(d):
    return sorted(p.name for p in d.rglob("*"))


def test_an_invalid_mode_config_is_refused_before_any_file(tmp_path, capsys):
    earlier = tmp_path / "earlier"
    earlier.mkdir()
    (earlier / "batch.json").write_text("{}")  # an earlier batch's directory
    (earlier / "compare.json").write_text("{}")
    argv = ["compare", PAPER, "--runs", "2", "--modes", "peer-info", "--graph", "custom"]
    assert main([*argv, "--out", str(earlier), "--force"]) == 2
    assert "edge" in capsys.readouterr().err
    assert _files(earlier) == ["batch.json", "compare.json"]
    fresh = tmp_path / "fresh"
    assert main([*argv, "--out", str(fresh)]) == 2
    assert not fresh.exists()


@pytest.mark.parametrize("modes", ["central", "central,info,ci"])
def test_graph_without_a_peer_mode_is_refused(tmp_path, capsys, modes):
    out = tmp_path / "out"
    assert (
        main(
            [
                "compare",
                PAPER,
                "--runs",
                "2",
                "--modes",
                modes,
                "--graph",
                "ring",
                "--out",
                str(out),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "--graph ring" in err and "peer" in err, err
    assert not out.exists()
