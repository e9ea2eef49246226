"""``covnet bench search`` and ``covnet bench multitarget`` generate their own problems: they run
from any directory (no ``configs/paper.yaml`` read, with or without ``--metric``) and refuse a
``--config`` they would not use."""

from __future__ import annotations

import json

import pytest

from covnet.cli.app import main


@pytest.mark.parametrize(
    "argv",
    [
        ["bench", "search", "--sensors", "4", "--search", "greedy", "--metric", "kl"],
        ["bench", "multitarget", "--sensors", "16", "--targets", "3", "--search", "greedy",
         "--metric", "kl"],  # fmt: skip
        ["bench", "multitarget", "--sensors", "4", "--targets", "2", "--metric", "spectral"],
    ],
)
def test_runs_outside_the_checkout(argv, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # no configs/ here
    rc = main([*argv, "--problems", "1", "--repeat", "1", "--json"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    rows = [json.loads(line) for line in out.splitlines()]
    assert rows and {r["metric"] for r in rows} == {argv[argv.index("--metric") + 1]}


@pytest.mark.parametrize("target", ["search", "multitarget"])
def test_config_is_refused(target, capsys):
    assert main(["bench", target, "--config", "configs/paper.yaml"]) == 2
    err = capsys.readouterr().err
    assert f"--config: bench {target} does not take this option" in err


@pytest.mark.parametrize(
    ("argv", "default"),
    [
        (["bench", "up"], "configs/paper.yaml"),
        (["bench"], "configs/paper.yaml"),
        (["bench", "cluster"], "configs/latency.yaml"),
    ],
)
def test_a_default_config_missing_here_says_to_give_one(argv, default, tmp_path, monkeypatch,
                                                        capsys):  # fmt: skip
    """Outside the checkout the benches that read a config said only "invalid config
    configs/paper.yaml: cannot read file", as if the user had named it."""
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"--config: not given, and the default {default} is not in this directory" in err
    assert "--config PATH" in err
