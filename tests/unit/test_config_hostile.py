"""Config files no one writes by hand, found by a structural fuzz: each gets exit 2 and a
message, at once (they ended in tracebacks, or hung):

- lists nested a thousand deep (PyYAML's composer, ``json.loads``: RecursionError);
- a YAML alias bomb (``&a1 [*a0 x 10]`` nine levels: 10^9 values from ten lines): the message
  quoted the refused value whole, and ``check`` printed for minutes; any such expansion is now
  refused by size, and a quoted value is cut short;
- an integer too large for a float as a link delay (the core's OverflowError)."""

from __future__ import annotations

import time

import pytest

from covnet.config import MAX_CONFIG_VALUES, ConfigError, _short, read_yaml
from covnet.covariance_control.config import load
from tests.conftest import REPO

PAPER = (REPO / "configs" / "paper.yaml").read_text()


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_nesting_a_thousand_deep_is_a_config_error(tmp_path, suffix):
    p = tmp_path / f"deep{suffix}"
    p.write_text('{"seed": ' + "[" * 1000 + "]" * 1000 + "}")
    with pytest.raises(ConfigError, match="nested too deeply"):
        read_yaml(p)


def test_an_alias_bomb_is_refused_by_its_size_at_once(tmp_path):
    lines = ["x0: &a0 [1,1,1,1,1,1,1,1,1,1]"]
    lines += [f"x{i}: &a{i} [" + ",".join([f"*a{i - 1}"] * 10) + "]" for i in range(1, 9)]
    p = tmp_path / "bomb.yaml"
    p.write_text("\n".join(lines) + "\nname: paper\nseed: *a8\n")
    t0 = time.process_time()
    with pytest.raises(ConfigError, match=f"more than {MAX_CONFIG_VALUES:,} values"):
        read_yaml(p)
    assert time.process_time() - t0 < 30  # (it did not end; generous for a loaded machine)


def test_a_refused_value_is_quoted_short(tmp_path):
    assert len(_short(list(range(10**6)))) < 100
    assert len(_short("x" * 5000)) < 100
    p = tmp_path / "c.yaml"
    p.write_text(PAPER.replace("name: paper", "name: [" + ", ".join(["abc"] * 5000) + "]"))
    with pytest.raises(ConfigError) as info:
        load(p)
    assert "name" in str(info.value) and len(str(info.value)) < 2000


@pytest.mark.parametrize(
    "delay",
    [
        "{kind: constant, value_s: 1" + "0" * 400 + "}",
        "{kind: empirical, samples_s: [0.1, 1" + "0" * 400 + "]}",
    ],
)
def test_an_integer_beyond_a_float_as_a_delay_is_a_config_error(tmp_path, delay):
    p = tmp_path / "c.yaml"
    p.write_text(PAPER + f"\nnetwork:\n  latency:\n    uplink:\n      delay: {delay}\n")
    with pytest.raises(ConfigError, match="magnitude at most"):
        load(p)


@pytest.mark.parametrize(
    ("edit", "where", "says"),
    [
        ("allocation:\n  metrics: [spectral, spectral, svd]", "allocation.metrics", "duplicate"),
        ("allocation:\n  required: [S1, S1]", "allocation.required", "duplicate"),
        ("allocation:\n  excluded: [S8, S8]", "allocation.excluded", "duplicate"),
        (
            "fusion:\n  mode: peer\n  peer: {graph: custom, edges: [[S1, S2], [S2, S1]]}",
            "fusion.peer.edges[1]",
            "the link of edges[0] again",
        ),
        ("fusion:\n  mode: peer\n  peer: {graph: ring, hub: S3}", "fusion.peer.hub", "star"),
        ("allocation:\n  policy: random\n  budget: 100", "allocation.budget", "the 8 sensors"),
    ],
)
def test_a_list_entry_given_twice_or_a_key_with_no_effect_is_named(tmp_path, edit, where, says):
    """A metric named twice ran once while config.json (and its hash) kept both; a repeated
    required or excluded sensor or peer link, and a star's hub on another graph, were taken
    without a word."""
    import yaml

    raw = yaml.safe_load(PAPER)
    for key, value in yaml.safe_load(edit).items():
        raw[key] = {**raw.get(key, {}), **value}
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigError) as info:
        load(p)
    assert any(w == where and says in m for w, m in info.value.problems), info.value.problems
