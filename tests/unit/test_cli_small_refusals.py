"""Small command-line defects a hunt through every option found: an option with an alias given
twice (``covnet compare --runs 2 --seeds 3`` ran 3 seeds without a word), an option silently
raised, a table header printed before a refusal, a refusal naming options the command does not
have."""

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


def test_a_refused_bench_prints_no_table_header(capsys):
    """``bench multitarget --targets 99`` printed its table's header to stdout, then refused."""
    assert main(["bench", "multitarget", "--targets", "99"]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and "--targets: 1 to" in captured.err


def test_a_refused_option_names_only_the_commands_options(tmp_path, capsys):
    """``covnet mc`` of a mobile config with ``--metric`` said "(its options: --seed,
    --solver)": mc has no --solver; then "(its options: --seed)", and its mc refuses --seed
    too (it runs seeds 0..N-1)."""
    mobile = str(REPO / "configs" / "mobile.yaml")
    for option in (["--metric", "kl"], ["--fusion", "ci"]):
        assert main(["mc", mobile, *option, "--out", str(tmp_path / "m")]) == 2
        err = capsys.readouterr().err
        assert "(its options: none)" in err, err
    assert main(["mc", mobile, "--seed", "3", "--out", str(tmp_path / "m")]) == 2
    assert "runs seeds 0..N-1" in capsys.readouterr().err
    assert main(["run", mobile, "--metric", "kl", "--out", str(tmp_path / "r")]) == 2
    assert "(its options: --seed, --solver)" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv,message",
    [
        (["run", PAPER, "--out", ""], "--out: empty"),
        (["up", PAPER, "--nodes", ""], "--nodes: empty"),
    ],
)
def test_an_empty_value_is_refused(tmp_path, monkeypatch, capsys, argv, message):
    """``--out ""`` wrote into the working directory; ``--nodes ""`` started every process."""
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    assert message in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_a_bench_count_given_twice_is_refused_and_a_metric_named_twice_timed_once(
    monkeypatch, capsys
):
    """``--sensors 8,8`` timed the same size twice; ``--metric kl --metric kl`` gave two rows
    of the same metric (covnet run takes a metric named twice once)."""
    with pytest.raises(SystemExit) as exc:
        main(["bench", "alloc", "--sensors", "8,8"])
    assert exc.value.code == 2
    assert "a count given twice in '8,8'" in capsys.readouterr().err
    from covnet.covariance_control import commands

    seen = []
    monkeypatch.setattr(commands, "bench_alloc", lambda args, sc: seen.append(args.metric) or 0)
    assert main(["bench", "alloc", "--sensors", "8", "--metric", "kl", "--metric", "kl"]) == 0
    assert seen == [["kl"]]


def test_a_live_view_of_a_peer_run_is_refused(tmp_path, capsys):
    """``covnet up --fusion peer --foxglove`` advertised the visual channels and sent nothing:
    they draw the fusion centre's scans, and a peer run has none."""
    out = tmp_path / "up"
    argv = ["up", PAPER, "--fusion", "peer", "--foxglove", "127.0.0.1:18771", "--out", str(out)]
    assert main(argv) == 2
    assert "--foxglove: fusion.mode peer has no fusion centre" in capsys.readouterr().err
    assert not out.exists()


def test_nodes_recorder_without_a_recording_is_refused(tmp_path, capsys):
    """``covnet up --nodes recorder`` with ``network.record: false`` started nothing and
    exited 0."""
    import yaml

    data = yaml.safe_load((REPO / "configs" / "paper.yaml").read_text())
    data["network"] = {"record": False}
    cfg = tmp_path / "c.yaml"
    cfg.write_text(yaml.safe_dump(data))
    argv = ["up", str(cfg), "--nodes", "recorder", "--router", "tcp/127.0.0.1:7447"]
    assert main([*argv, "--out", str(tmp_path / "o")]) == 2
    assert "network.record is false" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_minus_zero_is_zero_in_a_config(paper_path):
    """``-0.0`` and ``0.0`` gave two config hashes for one run (the sign of zero was kept)."""
    import math

    import yaml

    from covnet.covariance_control.config import config_hash, from_dict

    data = yaml.safe_load(paper_path.read_text())
    data["target"]["initial_position_m"] = [0.0, -0.0]
    sc = from_dict(data)
    assert math.copysign(1.0, sc.target.initial_position_m[1]) == 1.0
    data["target"]["initial_position_m"] = [0.0, 0.0]
    assert config_hash(from_dict(data)) == config_hash(sc)
