"""The run id hosts derive without ``--run`` (:func:`covnet.processes.process.default_run_id`)
agrees exactly where the config identity (:func:`covnet.processes.node_kit.config_id`) does:
``--metric`` on the manager's host only, or per-host ``network.router`` / ``network.connect``
copies, gave two run ids and the hosts never met (hunt 14)."""

from __future__ import annotations

from types import SimpleNamespace

import yaml

from covnet.processes.node_kit import config_id
from covnet.processes.process import default_run_id, load_config


def _loaded(path, metric=None, seed=None):
    args = SimpleNamespace(config=str(path), seed=seed, metric=metric, fusion=None, solver=None)
    return load_config(args)[1]


def test_the_default_run_id_agrees_where_the_identity_does(tmp_path, paper_path):
    data = yaml.safe_load(paper_path.read_text())
    a, b, c = tmp_path / "a.yaml", tmp_path / "b.yaml", tmp_path / "c.yaml"
    a.write_text(yaml.safe_dump({**data, "network": {"router": "tcp/127.0.0.1:17447"}}))
    b.write_text(yaml.safe_dump({**data, "network": {"connect": "tcp/127.0.0.1:17447"}}))
    both = {"router": "tcp/127.0.0.1:7000", "connect": "tcp/127.0.0.1:17447"}
    c.write_text(yaml.safe_dump({**data, "network": both}))
    hosts = [_loaded(a), _loaded(a, metric=["spectral"]), _loaded(b), _loaded(c),
             _loaded(paper_path), _loaded(paper_path, metric=["svd", "abs_trace"])]  # fmt: skip
    assert len({config_id(cfg) for cfg in hosts}) == 1  # the identity check lets them in
    ids = {default_run_id(cfg) for cfg in hosts}
    assert len(ids) == 1 and ids.pop().startswith(f"{data['name']}-"), ids
    # another seed: another identity, another run id
    other = _loaded(a, seed=data["seed"] + 1)
    assert config_id(other) != config_id(hosts[0])
    assert default_run_id(other) != default_run_id(hosts[0])
