"""How the batch commands (``covnet mc`` of every kind, ``sweep``, ``compare``) and ``covnet up``
end when a Ctrl-C lands after every run finished: while the table is written, or while the
figures are drawn.  A Ctrl-C while ``montecarlo.json`` was written left no table and a
``run.json`` without ``status``; one while drawing ended with "interrupted" only, the figures
missing and ``run.json`` saying "every run done".  Each moment is made deterministic by a
writer or a figure function that raises ``KeyboardInterrupt``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import yaml
from test_surveillance_run import base

from covnet.cli.app import main

REPO = Path(__file__).resolve().parents[2]


def _config(tmp_path: Path, name: str, **changes: Any) -> Path:
    data = yaml.safe_load((REPO / "configs" / f"{name}.yaml").read_text())
    for key, value in changes.items():
        data[key] = {**data.get(key, {}), **value} if isinstance(value, dict) else value
    path = tmp_path / f"{name}-short.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _paper(tmp_path: Path) -> Path:
    return _config(tmp_path, "paper", scans=5, sweep={
        "delay_ms": [0.0], "loss": [0.0], "modes": ["central"], "account_for_loss": [False],
        "seeds": 2,
    })  # fmt: skip


def _mobile(tmp_path: Path) -> Path:
    return _config(tmp_path, "mobile", scans=4)


def _passive(tmp_path: Path) -> Path:
    return _config(tmp_path, "passive", montecarlo={
        "trials": 2, "formations": ["cross"], "spacings_km": [1.0], "sigmas_mrad": [3.0],
        "clutter": [False], "methods": ["cot", "greedy"], "workers": 1,
    })  # fmt: skip


def _surveillance(tmp_path: Path) -> Path:
    data = base(scans=8) | {"sweep": {"search_weight": [0.0, 30.0], "seeds": 2}}
    path = tmp_path / "surveillance-short.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


#: (command line before --out, the table it writes, the module and writer to cut)
TABLE_WRITES = {
    "mc": (lambda p: ["mc", str(_paper(p)), "--trials", "3", "--workers", "1"],
           "montecarlo.json", "covnet.covariance_control.montecarlo", "write_json"),
    "mobile mc": (lambda p: ["mc", str(_mobile(p)), "--trials", "2", "--workers", "1"],
                  "montecarlo.json", "covnet.mobile.montecarlo", "write_json"),
    "passive mc": (lambda p: ["mc", str(_passive(p)), "--workers", "1"],
                   "results.json", "covnet.passive.montecarlo", "write_json"),
    "sweep": (lambda p: ["sweep", str(_paper(p)), "--workers", "1"],
              "sweep.json", "covnet.covariance_control.sweep", "write_table"),
    "compare": (lambda p: ["compare", str(_paper(p)), "--modes", "central,ci", "--runs", "2",
                           "--workers", "1"],
                "compare.json", "covnet.covariance_control.compare", "write_table"),
    "surveillance sweep": (lambda p: ["sweep", str(_surveillance(p)), "--workers", "1"],
                           "sweep.json", "covnet.covariance_control.batch_commands",
                           "write_rows"),
}  # fmt: skip


def _cut(monkeypatch, module: str, name: str, table: str, times: int) -> list[str]:
    """``module.name`` raises KeyboardInterrupt the first ``times`` times it is given the path
    ``table`` (a writer ``(path, ...)``) or, for a table writer ``(out, ...)``, any call."""
    import importlib

    mod = importlib.import_module(module)
    real = getattr(mod, name)
    cuts: list[str] = []

    def cut(first: Any, *rest: Any, **kw: Any) -> Any:
        hit = Path(first).name == table if name == "write_json" else True
        if hit and len(cuts) < times:
            cuts.append(str(first))
            raise KeyboardInterrupt
        return real(first, *rest, **kw)

    monkeypatch.setattr(mod, name, cut)
    return cuts


def _info(out: Path) -> dict[str, Any]:
    info = json.loads((out / "run.json").read_text())
    assert isinstance(info, dict)
    return info


@pytest.mark.parametrize("command", list(TABLE_WRITES))
def test_a_ctrl_c_while_the_table_is_written_records_it_and_the_same_command_finishes(
    command, tmp_path, monkeypatch, capsys
):
    """Every run done, a Ctrl-C while the table was written: the table is written whole,
    ``run.json`` says ``interrupted``, stderr that the same command finishes it; exit 130.
    The same command then completes without running a trial again."""
    argv_of, table, module, writer = TABLE_WRITES[command]
    out = tmp_path / "out"
    argv = [*argv_of(tmp_path), "--out", str(out), "--no-figures"]
    with monkeypatch.context() as m:
        cuts = _cut(m, module, writer, table, times=1)
        assert main(argv) == 130
    assert cuts, "the writer was not reached"
    err = capsys.readouterr().err
    info = _info(out)
    assert info["status"] == "interrupted", info
    assert "while the results were written" in info["ended"]
    assert info["runs_completed"] == info["runs_total"]
    assert "holds the whole table" in err and f"--out {out} finishes it" in err, err
    assert "Traceback" not in err
    first = json.loads((out / table).read_text())
    assert main(argv) == 0
    info = _info(out)
    assert info["status"] == "completed" and info["runs_run"] == 0, info  # no trial again
    again = json.loads((out / table).read_text())
    assert again.get("rows", again.get("per_seed")) == first.get("rows", first.get("per_seed"))


def test_a_second_ctrl_c_while_the_table_is_written_again_still_records_it(
    tmp_path, monkeypatch, capsys
):
    """The table's second write is interrupted too: no table, but ``run.json`` says
    ``interrupted`` and stderr says so."""
    argv_of, table, module, writer = TABLE_WRITES["mc"]
    out = tmp_path / "out"
    argv = [*argv_of(tmp_path), "--out", str(out), "--no-figures"]
    with monkeypatch.context() as m:
        _cut(m, module, writer, table, times=2)
        assert main(argv) == 130
    err = capsys.readouterr().err
    assert _info(out)["status"] == "interrupted"
    assert not (out / table).exists()
    assert "may be incomplete" in err and "finishes it" in err, err
    assert main(argv) == 0 and _info(out)["status"] == "completed"


#: (command line before --out, the table, the figure module and function to cut, a figure
#: ``covnet plot`` draws again)
FIGURES = {
    "mc": (TABLE_WRITES["mc"][0], "montecarlo.json", "covnet.covariance_control.plots",
           "mc_figure", "montecarlo.png"),
    "mobile mc": (TABLE_WRITES["mobile mc"][0], "montecarlo.json", "covnet.mobile.plots",
                  "mc_figure", "fig_mobile_mc.png"),
    "passive mc": (TABLE_WRITES["passive mc"][0], "results.json", "covnet.passive.plots",
                   "mc_figures", "fig_time.png"),
    "compare": (TABLE_WRITES["compare"][0], "compare.json", "covnet.covariance_control.compare",
                "make_figure", "compare.png"),
    "surveillance sweep": (TABLE_WRITES["surveillance sweep"][0], "sweep.json",
                           "covnet.covariance_control.surveillance_batch", "sweep_figure",
                           "sweep.png"),
}  # fmt: skip


@pytest.mark.parametrize("command", list(FIGURES))
def test_a_ctrl_c_while_the_figures_are_drawn_keeps_the_complete_results(
    command, tmp_path, monkeypatch, capsys
):
    """``run.json`` stays ``completed`` and says the figures were interrupted, stderr says
    that the directory holds the complete results and ``covnet plot`` draws them (as
    ``covnet run`` does), and ``covnet plot`` does."""
    argv_of, table, module, name, figure = FIGURES[command]
    out = tmp_path / "out"
    with monkeypatch.context() as m:
        _cut(m, module, name, table, times=1)
        assert main([*argv_of(tmp_path), "--out", str(out)]) == 130
    err = capsys.readouterr().err
    info = _info(out)
    assert info["status"] == "completed", info
    assert info["ended"] == "every run done (figures interrupted)"
    assert (out / table).is_file()
    assert f"holds the complete results (covnet plot {out} draws the figures)" in err, err
    assert not (out / figure).exists()
    assert main(["plot", str(out)]) == 0 and (out / figure).is_file()


def test_covnet_up_interrupted_while_drawing_says_so_in_run_json(tmp_path, monkeypatch, capsys):
    """``covnet up``: the network's run is complete (``run.json``: ``every scan done``), a
    Ctrl-C while its figures are drawn (after the launcher's ``up``; here a stand-in that
    writes the run as the manager does) ended with "interrupted" only and ``run.json``
    unchanged."""
    from covnet.covariance_control import plots
    from covnet.processes import up as up_module
    from covnet.runs.rundir import record_end

    def up(kind: Any, cfg: Any, config: str, out: Path, **kw: Any) -> int:
        assert kind.run(cfg, out, figures=False) == 0
        record_end(out, "completed", "every scan done")
        return 0

    def interrupted(out: Path) -> list[Path]:
        raise KeyboardInterrupt

    out = tmp_path / "up"
    with monkeypatch.context() as m:
        m.setattr(up_module, "up", up)
        m.setattr(plots, "make_figures", interrupted)
        assert main(["up", str(_paper(tmp_path)), "--out", str(out)]) == 130
    err = capsys.readouterr().err
    info = _info(out)
    assert (info["status"], info["ended"]) == ("completed", "every scan done (figures interrupted)")
    assert f"interrupted while drawing the figures: {out} holds the complete results" in err
    assert main(["plot", str(out)]) == 0 and list(out.glob("*.png"))


@pytest.mark.parametrize(
    "argv, function",
    [
        (lambda p: ["sweep", str(_surveillance(p)), "--workers", "1"], "weight_sweep"),
        (lambda p: ["compare", str(_surveillance(p)), "--policies", "all_on,random", "--budget",
                    "2", "--runs", "2", "--workers", "1"], "policy_compare"),
    ],
)  # fmt: skip
def test_a_surveillance_batch_interrupted_while_it_runs_records_it(
    argv, function, tmp_path, monkeypatch, capsys
):
    """``covnet sweep`` / ``compare --policies`` of a surveillance config interrupted while its
    trials ran left no run.json and no word that the same command resumes."""
    from covnet.batches.pool import BatchInterrupted
    from covnet.covariance_control import surveillance_batch as sb

    def interrupted(*args: Any, out: Path, **kw: Any) -> Any:
        (out / "trials").mkdir(parents=True, exist_ok=True)
        (out / "trials" / "one.json").write_text("{}")  # a finished trial, kept
        raise BatchInterrupted({(0, 1): {}}, 4)

    monkeypatch.setattr(sb, function, interrupted)
    out = tmp_path / "out"
    assert main([*argv(tmp_path), "--out", str(out)]) == 130
    info = _info(out)
    assert info["status"] == "interrupted" and info["runs_completed"] == 1, info
    assert "resumes" in capsys.readouterr().err
