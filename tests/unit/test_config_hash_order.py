"""``allocation.required`` and ``excluded`` are sets: written in any order they are one config
(one hash, one identity on the bus), and run directories hashed as written by older covnets
are still their config's."""

import json

import yaml

from covnet import kinds
from covnet.cli import main
from covnet.config import hash_of, read_yaml
from covnet.processes.node_kit import config_id
from tests.conftest import PAPER


def _paper(**allocation):
    data = read_yaml(PAPER)
    data["scans"] = 6
    data["allocation"] = {**data["allocation"], **allocation}
    return kinds.from_dict(data, "test")[1]


def test_required_and_excluded_in_any_order_are_one_config():
    a = _paper(required=["S3", "S1"], excluded=["S8", "S5"])
    b = _paper(required=["S1", "S3"], excluded=["S5", "S8"])
    assert kinds.config_hash(a) == kinds.config_hash(b)
    assert config_id(a) == config_id(b)  # two hosts' copies meet and agree
    data = kinds.of(a).normalised(a)
    assert data["allocation"]["required"] == ["S1", "S3"]  # the order of sensors:
    assert data["allocation"]["excluded"] == ["S5", "S8"]
    # the older hash is the lists' as written; none where they were in order already
    assert kinds.config_hashes(b) == (kinds.config_hash(b),)
    (older,) = kinds.of(a).older_hashes(a)
    as_written = {**data, "allocation": {**data["allocation"], "required": ["S3", "S1"],
                                         "excluded": ["S8", "S5"]}}  # fmt: skip
    assert older == hash_of(as_written) != kinds.config_hash(a)


def test_a_run_directory_an_older_covnet_hashed_as_written_is_still_its_configs(tmp_path):
    """``covnet plot`` of a run directory whose ``config.json`` lists ``required`` out of
    order and whose results carry the hash of the lists as written (what covnet wrote before)
    draws it; a hash of neither is still refused."""
    cfg = _paper(required=["S3", "S1"])
    path = tmp_path / "c.yaml"
    data = kinds.of(cfg).normalised(cfg)
    data["allocation"]["required"] = ["S3", "S1"]
    path.write_text(yaml.safe_dump(data))
    out = tmp_path / "run"
    assert main(["run", str(path), "--out", str(out), "--no-figures"]) == 0
    config = json.loads((out / "config.json").read_text())
    assert config["allocation"]["required"] == ["S1", "S3"]
    # as an older covnet left it: the config as written, the results hashed so
    (older,) = kinds.of(cfg).older_hashes(cfg)
    config["allocation"]["required"] = ["S3", "S1"]
    (out / "config.json").write_text(json.dumps(config))
    summary = json.loads((out / "summary.json").read_text())
    (out / "summary.json").write_text(json.dumps({**summary, "config_hash": older}))
    assert main(["plot", str(out)]) == 0
    (out / "summary.json").write_text(json.dumps({**summary, "config_hash": "0" * 16}))
    assert main(["plot", str(out)]) == 2
