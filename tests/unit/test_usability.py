"""A user's mistakes get a clear answer at once; nothing is overwritten or silently ignored
(issue 15): ``--out`` and ``--force`` for every command, what a run used is what its
``config.json`` says, every option validated before anything starts, ``--json`` is JSON, config
messages show root causes only, all at once."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from covnet.cli.app import main

REPO = Path(__file__).resolve().parents[2]
PAPER = REPO / "configs" / "paper.yaml"
MOBILE = REPO / "configs" / "mobile.yaml"
PASSIVE = REPO / "configs" / "passive.yaml"
LATENCY = REPO / "configs" / "latency.yaml"


def _short(tmp_path: Path, src: Path, name: str, **changes) -> Path:
    data = yaml.safe_load(src.read_text())
    for key, value in changes.items():
        if isinstance(value, dict) and isinstance(data.get(key), dict):
            data[key] = {**data[key], **value}
        else:
            data[key] = value
    p = tmp_path / f"{name}.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


@pytest.fixture
def short_paper(tmp_path):
    return _short(tmp_path, PAPER, "paper-short", scans=8, allocation={"metrics": ["spectral"]})


@pytest.fixture
def short_mobile(tmp_path):
    return _short(tmp_path, MOBILE, "mobile-short", scans=5, compare_exact=False)


@pytest.fixture
def tiny_passive(tmp_path):
    grid = {"trials": 1, "formations": ["cross"], "spacings_km": [1.0], "sigmas_mrad": [3.0]}
    grid |= {"clutter": [False], "methods": ["cot"], "workers": 1}
    return _short(tmp_path, PASSIVE, "passive-tiny", montecarlo=grid)


@pytest.fixture
def small_sweep(tmp_path):
    sweep = {"delay_ms": [0.0, 100.0], "loss": [0.0], "modes": ["central"]}
    sweep |= {"account_for_loss": [False], "seeds": 1}
    return _short(tmp_path, LATENCY, "sweep-small", scans=8, sweep=sweep)


def _stale(d: Path) -> Path:
    """``d`` made an earlier covnet output with a file the next run will not write."""
    d.mkdir(parents=True, exist_ok=True)
    (d / "config.json").write_text("{}")
    stale = d / "fig9_from_an_earlier_run.png"
    stale.write_text("old")
    (d / "replay").mkdir(exist_ok=True)
    (d / "replay" / "summary.json").write_text("{}")
    return stale


# --------------------------------------------------------------------------------------------
# --out and --force
# --------------------------------------------------------------------------------------------


def _commands(paths: dict[str, Path]) -> dict[str, list[str]]:
    return {
        "run": ["run", str(paths["paper"]), "--no-figures"],
        "mc-mobile": ["mc", str(paths["mobile"]), "--trials", "1"],
        "mc-passive": ["mc", str(paths["passive"])],
        "compare": ["compare", str(paths["paper"]), "--runs", "2", "--modes", "central"]
        + ["--workers", "1", "--no-figures"],
        "sweep": ["sweep", str(paths["sweep"]), "--workers", "1", "--no-figures"],
    }


@pytest.mark.parametrize("command", ["run", "mc-mobile", "mc-passive", "compare", "sweep"])
def test_out_is_never_overwritten_without_force_and_force_leaves_nothing_stale(
    command, tmp_path, short_paper, short_mobile, tiny_passive, small_sweep, capsys
):
    paths = {"paper": short_paper, "mobile": short_mobile}
    paths |= {"passive": tiny_passive, "sweep": small_sweep}
    argv = _commands(paths)[command]
    out = tmp_path / "out"
    stale = _stale(out)
    assert main([*argv, "--out", str(out)]) == 2
    assert "directory is not empty" in capsys.readouterr().err
    assert stale.exists()  # untouched
    assert main([*argv, "--out", str(out), "--force"]) == 0
    assert not stale.exists() and not (out / "replay").exists()
    assert (out / "config.json").read_text() != "{}"


def test_up_refuses_a_non_empty_out_before_starting_anything(tmp_path, capsys):
    out = tmp_path / "out"
    stale = _stale(out)
    assert main(["up", str(PAPER), "--out", str(out)]) == 2
    assert "directory is not empty" in capsys.readouterr().err
    assert stale.exists() and not (out / "processes.json").exists()


def test_force_never_empties_a_directory_covnet_did_not_write(tmp_path, short_paper, capsys):
    mine = tmp_path / "notes"
    mine.mkdir()
    (mine / "thesis.tex").write_text("precious")
    argv = ["run", str(short_paper), "--no-figures", "--force"]
    assert main([*argv, "--out", str(mine)]) == 2
    assert "not an output of covnet" in capsys.readouterr().err
    assert (mine / "thesis.tex").read_text() == "precious"


def test_force_never_empties_the_working_directory(tmp_path, short_paper, monkeypatch, capsys):
    _stale(tmp_path)
    monkeypatch.chdir(tmp_path)
    assert main(["run", str(short_paper), "--no-figures", "--force", "--out", "."]) == 2
    assert "holds the working directory" in capsys.readouterr().err
    assert (tmp_path / "config.json").exists()


# --------------------------------------------------------------------------------------------
# what a run used is what its config.json says
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "config,options",
    [
        ("paper", ["--seed", "7"]),
        ("paper", ["--metric", "svd"]),
        ("paper", ["--fusion", "info"]),
        ("mobile", ["--solver", "milp"]),
        ("mobile", ["--seed", "3"]),
        ("passive", ["--seed", "5"]),
    ],
    ids=lambda v: v if isinstance(v, str) else "-".join(v).strip("-"),
)
def test_rerunning_from_the_stored_config_reproduces_the_run(
    config, options, tmp_path, short_paper, short_mobile
):
    src = {"paper": short_paper, "mobile": short_mobile, "passive": PASSIVE}[config]
    first, again = tmp_path / "first", tmp_path / "again"
    assert main(["run", str(src), *options, "--out", str(first), "--no-figures"]) == 0
    assert main(["run", str(first / "config.json"), "--out", str(again), "--no-figures"]) == 0
    result = "association.json" if config == "passive" else "summary.json"
    assert (first / result).read_bytes() == (again / result).read_bytes()
    assert (first / "config.json").read_bytes() == (again / "config.json").read_bytes()


# --------------------------------------------------------------------------------------------
# options validated before anything starts
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "argv,message",
    [
        (["up", str(PAPER), "--router", "foo"], "--router: expected a zenoh endpoint"),
        (["up", str(PAPER), "--router", "tcp/1.2.3.4:99999"], "--router: the port must be"),
        (["up", str(PAPER), "--fusion", "peer", "--realtime"], "runs in lockstep only"),
        (["up", str(PAPER), "--speed", "10"], "--speed: scales the real-time clock"),
        (["up", str(PAPER), "--realtime", "--speed", "0"], "--speed: must be a finite number > 0"),
        # inf made every period 0: the manager failed before READY
        (["up", str(PAPER), "--realtime", "--speed", "inf"], "--speed: must be a finite number"),
        (["up", str(PAPER), "--nodes", "S1,S99"], "--nodes: unknown process 'S99'"),
        # without the manager here and with the default router (port 0: a free port of this
        # host), the sensors tried a port nothing listens on and failed to connect
        (["up", str(PAPER), "--nodes", "S1"], "--nodes S1: the manager (the network's router)"),
        (["up", str(PAPER), "--nodes", "sensors", "--router", "tcp/127.0.0.1:0"], "give --router"),
        (["up", str(PAPER), "--solver", "lp"], "--solver: a covariance-control scenario"),
        (["up", str(LATENCY)], "network.latency describes slow or lossy links"),
        # the live view's server ran inside the manager's namespace, out of the host's reach
        (["up", str(PAPER), "--netns", "--foxglove"], "--foxglove: with --netns the live view"),
        (["up", str(PASSIVE), "--netns", "--foxglove"], "--foxglove: with --netns the live"),
        (["run", str(PAPER), "--metric", "nope"], "--metric: unknown metric 'nope'"),
        (["run", str(PAPER), "--fusion", "gossip"], "--fusion: unknown fusion mode"),
        (["run", str(PASSIVE), "--metric", "spectral"], "--metric: a passive scenario"),
        (["run", str(MOBILE), "--solver", "simplex"], "--solver: unknown solver"),
        (["run", str(MOBILE), "--seed", "-1"], "--seed: must be >= 0"),
        (["mc", str(MOBILE), "--trials", "0"], "--trials: must be >= 1"),
        (["mc", str(MOBILE), "--trials", "-1"], "--trials: must be >= 1"),
        (["mc", str(PASSIVE), "--trials", "0"], "--trials: must be an integer >= 1"),
        (["mc", str(PAPER), "--trials", "0"], "--trials: must be >= 1"),
        (["mc", str(PAPER), "--workers", "0"], "--workers: must be >= 1"),
        (["bench", "up", "--repeat", "0"], "--repeat: must be >= 1"),
        (["bench", "--problems", "0"], "--problems: must be >= 1"),
        (["compare", str(MOBILE)], "compare: comparing fusion structures is not defined"),
        (["compare", str(PAPER), "--runs", "1"], "--runs: at least 2 runs"),
        (["sweep", str(PASSIVE)], "sweep: the network-latency sweep is not defined"),
        (["replay", str(REPO / "configs")], "not a recorded network run directory"),
    ],
    ids=lambda v: " ".join(v[:1] + v[2:]) if isinstance(v, list) else None,
)
def test_a_bad_option_is_one_line_exit_2_and_nothing_left_behind(
    argv, message, tmp_path, monkeypatch, capsys
):
    monkeypatch.chdir(tmp_path)  # a run directory would appear under ./runs
    out = tmp_path / "out"
    has_out = argv[0] in ("up", "run", "mc", "compare", "sweep")
    assert main([*argv, *(["--out", str(out)] if has_out else [])]) == 2
    err = capsys.readouterr().err
    assert message in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists() and not (tmp_path / "runs").exists()


# --------------------------------------------------------------------------------------------
# --json is JSON
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("command", ["compare", "sweep"])
def test_json_output_is_only_json(command, tmp_path, short_paper, small_sweep, capsys):
    argv = _commands(
        {"paper": short_paper, "sweep": small_sweep} | dict.fromkeys(("mobile", "passive"), PAPER)
    )[command]
    assert main([*argv, "--out", str(tmp_path / "o"), "--json"]) == 0
    out = capsys.readouterr().out
    rows = [json.loads(line) for line in out.splitlines()]  # every line parses
    assert rows and all(isinstance(r, dict) for r in rows)


# --------------------------------------------------------------------------------------------
# config messages: root causes, all at once
# --------------------------------------------------------------------------------------------


def test_config_problems_are_root_causes_all_at_once(tmp_path, capsys):
    data = yaml.safe_load(PAPER.read_text())
    data["filter"]["P0_diag"] = ["1.0e4", 100.0, 10000.0, 100.0]  # YAML 1.1 reads 1.0e4 as text
    data["target"]["accel_noise_std_mps2"] = -0.5
    data["sensors"][3]["id"] = "S1"
    data["allocation"]["metrics"] = ["spectral", "nope"]
    data["fusion"] = {"mode": "gossip"}
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(data))
    assert main(["check", str(p)]) == 2
    lines = capsys.readouterr().err.strip().splitlines()[1:]
    paths = [line.strip().split(":")[0] for line in lines]
    assert paths == [
        "target.accel_noise_std_mps2",
        "filter.P0_diag[0]",
        "sensors[3].id",
        "allocation.metrics[1]",
        "fusion.mode",
    ], lines
    assert "write 1.0e+4" in lines[1]
    assert "duplicate sensor id 'S1'" in lines[2]


@pytest.mark.parametrize(
    "text,hint",
    [
        ("1e4", "write 1.0e+4"),
        ("1.5E3", "write 1.5e+3"),
        ("1.0", "drop the quotes"),
        ("1e-9", "write 1.0e-9"),  # (was told to drop quotes it did not have)
        ("2E+5", "write 2.0e+5"),
        ("1.0e-9", "drop the quotes"),  # YAML reads it unquoted: it was quoted
    ],
)
def test_a_number_given_as_text_gets_the_hint_that_fits(tmp_path, capsys, text, hint):
    data = yaml.safe_load(PAPER.read_text())
    data["period_s"] = text
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(data))
    assert main(["check", str(p)]) == 2
    [line] = capsys.readouterr().err.strip().splitlines()[1:]
    assert line.strip().startswith(f"period_s: expected a number, got the string '{text}'")
    assert hint in line
    assert ("YAML 1.1" in line) != ("drop the quotes" in line)


@pytest.mark.parametrize(
    ("written", "read"), [("off", "'off'"), ("on", "'on'"), ("'off'", "'off'")]
)
def test_missed_command_off_and_on_as_the_readme_writes_them(tmp_path, capsys, written, read):
    """YAML 1.1 reads an unquoted off/on as false/true: ``missed_command: off`` was refused as
    ``got False``."""
    text = PAPER.read_text() + f"\nnetwork:\n  latency:\n    missed_command: {written}\n"
    p = tmp_path / "c.yaml"
    p.write_text(text)
    assert main(["check", str(p)]) == 0, capsys.readouterr().err
    assert f"missed_command: {read}" in capsys.readouterr().out


# --------------------------------------------------------------------------------------------
# covnet plot: every kind's directories
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "argv,figures",
    [
        (["run", "{paper}"], {"fig1_sensor_ellipses.png", "fig4_allocation_raster.png"}),
        (["run", "{mobile}"], {"fig_mobile_trajectories.png"}),
        (["run", str(PASSIVE)], {"scene.png"}),
        (["mc", "{mobile}", "--trials", "2"], {"fig_mobile_mc.png"}),
        (["mc", "{passive}"], {"fig_p_vs_d.png", "fig_time.png"}),
        (
            ["compare", "{paper}", "--runs", "2", "--modes", "central", "--workers", "1"],
            {"compare.png", "curves.png"},
        ),
        (["sweep", "{sweep}", "--workers", "1"], {"sweep.png", "curves.png"}),
    ],
    ids=["run-paper", "run-mobile", "run-passive", "mc-mobile", "mc-passive", "compare", "sweep"],
)
def test_plot_redraws_every_kind_of_directory(
    argv, figures, tmp_path, short_paper, short_mobile, tiny_passive, small_sweep, capsys
):
    paths = {"paper": short_paper, "mobile": short_mobile}
    paths |= {"passive": tiny_passive, "sweep": small_sweep}
    out = tmp_path / "out"
    argv = [a.format(**{k: str(v) for k, v in paths.items()}) for a in argv]
    assert main([*argv, "--out", str(out)]) == 0
    for f in figures:
        (out / f).unlink()
    capsys.readouterr()
    assert main(["plot", str(out)]) == 0
    assert {f for f in figures if (out / f).stat().st_size > 1000} == figures
    # a config.json edited after the run is not what the run computed: refused
    cfg = json.loads((out / "config.json").read_text())
    (out / "config.json").write_text(json.dumps({**cfg, "name": "edited"}))
    capsys.readouterr()
    assert main(["plot", str(out)]) == 2
    err = capsys.readouterr().err
    assert " hash " in err and "edited after" in err, err


def test_plot_says_what_a_directory_lacks(tmp_path, capsys):
    assert main(["plot", str(tmp_path)]) == 2
    assert "missing config.json" in capsys.readouterr().err
    (tmp_path / "config.json").write_text(
        json.dumps(yaml.safe_load((REPO / "configs" / "mobile.yaml").read_text()))
    )
    assert main(["plot", str(tmp_path)]) == 2
    assert "missing summary.json, arrays.npz" in capsys.readouterr().err


def _paper_dir_without_scans(tmp_path: Path, src: Path) -> Path:
    """What ``covnet up`` leaves when no scan was done (the manager writes no metric's run)."""
    from covnet.covariance_control import config as cc
    from covnet.covariance_control.results import write_run, write_targets_run

    sc = cc.load(src)
    out = tmp_path / f"{sc.name}-no-scans"
    if sc.multitarget:
        from covnet.covariance_control import targets

        write_targets_run(out, sc, targets.build(sc), {})
    else:
        from covnet.covariance_control.model import build_model
        from covnet.covariance_control.simulate import shared_trajectory

        write_run(out, sc, shared_trajectory(build_model(sc)), {})
    return out


@pytest.mark.parametrize(
    "src", [PAPER, REPO / "configs" / "multitarget.yaml"], ids=["paper", "targets"]
)
def test_plot_of_a_run_without_scans_says_so(tmp_path, capsys, src):
    out = _paper_dir_without_scans(tmp_path, src)
    assert main(["plot", str(out)]) == 2
    err = capsys.readouterr().err
    assert "no scan" in err and "Traceback" not in err, err


@pytest.mark.parametrize(
    "content", [b'{"name": "paper", "seed": ', b"\xff\xfe not text"], ids=["json", "utf-8"]
)
def test_plot_of_a_corrupt_config_json_is_a_message(tmp_path, short_paper, capsys, content):
    out = tmp_path / "out"
    assert main(["run", str(short_paper), "--no-figures", "--out", str(out)]) == 0
    (out / "config.json").write_bytes(content)
    capsys.readouterr()
    assert main(["plot", str(out)]) == 2
    err = capsys.readouterr().err
    assert "config.json" in err and "Traceback" not in err, err


def test_plot_refuses_a_config_json_edited_after_the_run(tmp_path, short_paper, capsys):
    out = tmp_path / "out"
    assert main(["run", str(short_paper), "--no-figures", "--out", str(out)]) == 0
    cfg = json.loads((out / "config.json").read_text())
    cfg["sensors"] = cfg["sensors"][1:]
    (out / "config.json").write_text(json.dumps(cfg))
    capsys.readouterr()
    assert main(["plot", str(out)]) == 2
    err = capsys.readouterr().err
    assert "config hash" in err and "summary.json" in err, err
    assert not (out / "fig1_sensor_ellipses.png").exists()
