"""``network.security``: config validation and the zenoh settings each process gets
(no zenoh session here; the settings are exercised for real in tests/integration/test_security.py).
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from test_security_certs import CA

from covnet.config import ConfigError
from covnet.covariance_control.config import config_hash, from_dict, load, normalised
from covnet.wire import messages as msg
from covnet.wire.bus import keyexpr_matches
from covnet.wire.security import (
    access_control,
    endpoint,
    file_problems,
    preflight,
    read_credentials,
    zenoh_settings,
)

RUN = "a1b2c3"


@pytest.fixture()
def lab(tmp_path: Path) -> Path:
    """A directory with a credentials file, a CA and certificates for manager, world, S1 and
    S2 (real ones: preflight parses them; made as in test_security_certs.py)."""
    (tmp_path / "creds.txt").write_text(
        "world:pw-world\nrecorder:pw-rec\n\nS1: pw1\nS2:pw:2\nintruder:x\n"
    )
    certs = tmp_path / "pki" / "certs"
    certs.mkdir(parents=True)
    ca = CA(tmp_path / "pki")
    for n in ("manager", "world", "S1", "S2"):
        ca.issue(certs, n)
    return tmp_path


def _data(paper, **security) -> dict:
    data = normalised(paper)
    data["sensors"] = data["sensors"][:2]
    data["network"]["record"] = False
    if security:
        data["network"]["security"] = security
    return data


def _problems(data: dict, base_dir: Path | None = None) -> dict[str, str]:
    with pytest.raises(ConfigError) as exc:
        from_dict(data, "t.yaml", base_dir=base_dir)
    return dict(exc.value.problems)


# --------------------------------------------------------------------------------------------
# config
# --------------------------------------------------------------------------------------------


def test_default_is_off_and_keeps_the_hash(paper):
    assert not paper.network.security.access_control
    assert paper.network.security.credentials_file is None
    assert paper.network.security.tls is None
    assert "security" not in normalised(paper)["network"]
    assert config_hash(paper) == config_hash(from_dict(normalised(paper)))
    assert zenoh_settings(paper.network, "sensor", "S1", listen=False) == {}
    assert zenoh_settings(paper.network, "manager", "manager", listen=True) == {}


def test_relative_paths_resolve_against_the_config_file(paper, lab, tmp_path_factory):
    data = _data(
        paper,
        access_control=True,
        credentials_file="creds.txt",
        tls={"ca": "pki/ca.pem", "cert_dir": "pki/certs"},
    )
    cfg = lab / "scenario.yaml"
    cfg.write_text(yaml.safe_dump(data))
    sc = load(cfg)
    sec = sc.network.security
    assert sec.credentials_file == str(lab / "creds.txt")
    assert sec.tls is not None and sec.tls.ca == str(lab / "pki" / "ca.pem")
    assert sec.tls.cert_dir == str(lab / "pki" / "certs")
    assert sec.tls.verify_name is True
    assert "security" in normalised(sc)["network"]
    # a copy with overrides (what --seed does) keeps the resolved paths
    from covnet.covariance_control.config import with_overrides

    assert with_overrides(sc, seed=5).network.security == sec


def test_copies_in_two_folders_agree_on_the_run_id(paper, lab, tmp_path):
    """Hosts started without --run agree on a run id derived from the config; with security
    its file paths are made absolute where the config lies, so copies of one config in two
    folders derived two run ids and the hosts never met."""
    import shutil

    from covnet.processes.process import default_run_id

    data = _data(paper, access_control=True, credentials_file="creds.txt")
    a, b = lab / "c.yaml", tmp_path / "hostB" / "c.yaml"
    b.parent.mkdir()
    for path in (a, b):
        path.write_text(yaml.safe_dump(data))
    shutil.copy(lab / "creds.txt", b.parent / "creds.txt")
    ra, rb = default_run_id(load(a)), default_run_id(load(b))
    assert ra == rb and ra.startswith(f"{data['name']}-"), (ra, rb)
    data["seed"] += 1  # another config: another run id
    b.write_text(yaml.safe_dump(data))
    assert default_run_id(load(b)) != ra


@pytest.mark.parametrize(
    "security, path, fragment",
    [
        ({"acces_control": True}, "network.security.acces_control", "unknown key"),
        (
            {"tls": {"ca": "pki/ca.pem", "cert_dir": "pki/certs", "key": "x"}},
            "network.security.tls.key",
            "unknown key",
        ),
        ({"access_control": "true"}, "network.security.access_control", "valid boolean"),
        ({"access_control": True}, "network.security.access_control", "needs node identities"),
        ({"tls": {"ca": "pki/ca.pem"}}, "network.security.tls.cert_dir", "missing required key"),
        ({"credentials_file": ""}, "network.security.credentials_file", "at least 1 character"),
    ],
    ids=["typo", "tls-typo", "strict-bool", "acl-without-identity", "cert-dir-required", "empty"],
)
def test_security_config_errors_name_the_field(paper, lab, security, path, fragment):
    problems = _problems(_data(paper, **security), base_dir=lab)
    assert path in problems, problems
    assert fragment in problems[path]


@pytest.mark.parametrize(
    "security, path, fragment",
    [
        ({"credentials_file": "nope.txt"}, "network.security.credentials_file", "does not exist"),
        ({"credentials_file": "bad.txt"}, "network.security.credentials_file", "line 2"),
        (
            {"tls": {"ca": "missing.pem", "cert_dir": "pki/certs"}},
            "network.security.tls.ca",
            "does not exist",
        ),
        (
            {"tls": {"ca": "creds.txt", "cert_dir": "pki/certs"}},
            "network.security.tls.ca",
            "not a PEM file",
        ),
        (
            {"tls": {"ca": "pki/ca.pem", "cert_dir": "nowhere"}},
            "network.security.tls.cert_dir",
            "not a directory",
        ),
    ],
    ids=["no-credentials-file", "bad-credentials-line", "no-ca", "ca-not-pem", "no-cert-dir"],
)
def test_missing_files_are_reported_when_a_process_needs_them(paper, lab, security, path, fragment):
    """The config still loads (a run directory's config.json must stay readable where the
    keys are gone); every process, and ``covnet up`` before it starts any, reports the file."""
    (lab / "bad.txt").write_text("world:pw\nS1\n")
    sc = from_dict(_data(paper, **security), base_dir=lab)
    assert dict(file_problems(sc.network))[path].count(fragment) == 1
    with pytest.raises(ConfigError) as exc:
        zenoh_settings(sc.network, "sensor", "S1", listen=False, source="lab.yaml")
    assert fragment in dict(exc.value.problems)[path] and "lab.yaml" in str(exc.value)
    with pytest.raises(ConfigError) as exc:
        preflight(sc, ["manager", "world", "S1"], "lab.yaml")
    assert fragment in dict(exc.value.problems)[path]


def test_preflight_lists_every_missing_key_and_password(paper, lab):
    sc = from_dict(
        _data(
            paper,
            credentials_file="creds.txt",
            tls={"ca": "pki/ca.pem", "cert_dir": "pki/certs"},
        ),
        base_dir=lab,
    )
    preflight(sc, ["manager", "world", "S1", "S2"])
    (lab / "pki" / "certs" / "S2.key").unlink()
    (lab / "creds.txt").write_text("world:a\nS2:b\n")
    with pytest.raises(ConfigError) as exc:
        preflight(sc, ["manager", "world", "S1", "S2"], "lab.yaml")
    text = str(exc.value)
    assert "no password for the node(s) ['S1']" in text  # the router's check
    assert "no password for this node ('S1')" in text
    assert "S2.key" in text and "does not exist" in text


def test_credentials_errors_never_show_passwords(paper, lab):
    (lab / "bad.txt").write_text("S1:secret-one\nS1:secret-two\n")
    sc = from_dict(_data(paper, credentials_file="bad.txt"), base_dir=lab)
    text = dict(file_problems(sc.network))["network.security.credentials_file"]
    assert "appears twice" in text and "secret" not in text


def test_tls_endpoints_need_tls_and_tls_needs_tcp(paper, lab):
    data = _data(paper)
    data["network"]["router"] = "tls/127.0.0.1:7447"
    assert "needs network.security.tls" in _problems(data, lab)["network.router"]
    data["network"]["router"] = "udp/127.0.0.1:7447"
    data["network"]["security"] = {"tls": {"ca": "pki/ca.pem", "cert_dir": "pki/certs"}}
    assert "use a tcp/ or tls/ endpoint" in _problems(data, lab)["network.router"]


@pytest.mark.parametrize(
    ("tls", "option", "endpoint", "needle"),
    [
        (True, "--router", "udp/127.0.0.1:7447", "use a tcp/ or tls/ endpoint"),
        (False, "--router", "tls/127.0.0.1:7447", "a tls/ endpoint needs"),
    ],
)
def test_command_line_endpoints_are_held_to_the_security_too(
    paper, lab, capsys, tls, option, endpoint, needle
):
    """``covnet up --router udp/...`` with ``network.security.tls`` ran the whole network
    over plain UDP (a client with no certificate read every message); the same endpoint in
    the config was refused.  Now the command line's endpoints are checked as the config's."""
    from covnet.cli.app import main

    sec = {"tls": {"ca": "pki/ca.pem", "cert_dir": "pki/certs"}} if tls else {}
    data = _data(paper, credentials_file="creds.txt", **sec)
    cfg = lab / "c.yaml"
    cfg.write_text(yaml.safe_dump(data))
    assert main(["up", str(cfg), option, endpoint, "--out", str(lab / "out")]) == 2
    err = capsys.readouterr().err
    assert f"{option}: " in err and needle in err, err
    assert not (lab / "out").exists()


def test_a_nodes_command_line_endpoint_is_held_to_the_security(paper, lab):
    """``python -m manager --listen`` / ``python -m sensors --connect``: the same check."""
    import argparse

    from covnet.errors import UsageError
    from covnet.processes.process import resolve_run

    sec = {"tls": {"ca": "pki/ca.pem", "cert_dir": "pki/certs"}}
    cfg = from_dict(_data(paper, **sec), "t.yaml", base_dir=lab)
    for option in ("listen", "connect"):
        args = argparse.Namespace(run=None, listen=None, connect=None)
        setattr(args, option, "udp/127.0.0.1:7447")
        with pytest.raises(UsageError, match=f"--{option}: with network.security.tls"):
            resolve_run(args, cfg)


@pytest.mark.parametrize("name", ["manager", "world", "recorder"])
def test_reserved_sensor_ids(paper, lab, name):
    """A node's own name as a sensor id is refused with or without security (without it,
    check and run took it and covnet up failed with a traceback)."""
    data = _data(paper, credentials_file="creds.txt")
    data["sensors"][1]["id"] = name
    assert "network's own nodes" in _problems(data, lab)["sensors[1].id"]
    data["network"].pop("security")
    assert "network's own nodes" in _problems(data, lab)["sensors[1].id"]


def test_read_credentials_parses_like_zenoh(lab):
    creds = read_credentials(lab / "creds.txt")
    assert creds["S1"] == "pw1" and creds["S2"] == "pw:2" and creds["world"] == "pw-world"
    for bad, why in (("S1\n", "expected"), (":pw\n", "empty user"), ("S1:\n", "empty password")):
        (lab / "x.txt").write_text(bad)
        with pytest.raises(ValueError, match=why):
            read_credentials(lab / "x.txt")


# --------------------------------------------------------------------------------------------
# zenoh settings
# --------------------------------------------------------------------------------------------


def _net(paper, lab, **security):
    return from_dict(_data(paper, **security), base_dir=lab).network


def test_password_settings(paper, lab):
    net = _net(paper, lab, credentials_file="creds.txt")
    assert zenoh_settings(net, "sensor", "S2", listen=False) == {
        "transport/auth/usrpwd/user": "S2",
        "transport/auth/usrpwd/password": "pw:2",
    }
    router = zenoh_settings(net, "manager", "manager", listen=True, sensor_ids=("S1", "S2"))
    assert router == {"transport/auth/usrpwd/dictionary_file": str(lab / "creds.txt")}
    with pytest.raises(ConfigError) as exc:
        zenoh_settings(net, "sensor", "S3", listen=False, source="lab.yaml")
    assert "lab.yaml" in str(exc.value) and "no password for this node ('S3')" in str(exc.value)
    with pytest.raises(ConfigError, match=r"no password for the node\(s\) \['S3'\]"):
        zenoh_settings(net, "manager", "manager", listen=True, sensor_ids=("S1", "S3"))


def test_a_host_shares_one_session_only_between_sensors_of_the_same_settings(paper, lab):
    """sensors.host: security off, one session for every hosted sensor; per-node passwords,
    a session each (each sensor logs in as itself)."""
    from types import SimpleNamespace

    from sensors.host import one_session

    args = SimpleNamespace(config="t.yaml")
    off = from_dict(_data(paper), base_dir=lab)
    assert one_session(["S1", "S2"], args, off)
    pw = from_dict(_data(paper, credentials_file="creds.txt"), base_dir=lab)
    assert not one_session(["S1", "S2"], args, pw)
    assert one_session(["S2"], args, pw)


def test_tls_settings_and_endpoints(paper, lab):
    net = _net(paper, lab, tls={"ca": "pki/ca.pem", "cert_dir": "pki/certs", "verify_name": False})
    certs = lab / "pki" / "certs"
    assert zenoh_settings(net, "world", "world", listen=False) == {
        "transport/link/tls/root_ca_certificate": str(lab / "pki" / "ca.pem"),
        "transport/link/tls/connect_certificate": str(certs / "world.pem"),
        "transport/link/tls/connect_private_key": str(certs / "world.key"),
        "transport/link/tls/enable_mtls": True,
        "transport/link/tls/verify_name_on_connect": False,
    }
    router = zenoh_settings(net, "manager", "manager", listen=True)
    assert router["transport/link/tls/listen_certificate"] == str(certs / "manager.pem")
    assert router["transport/link/tls/listen_private_key"] == str(certs / "manager.key")
    assert router["transport/link/tls/enable_mtls"] is True
    with pytest.raises(ConfigError, match=r"network.security.tls.cert_dir: this node's certif"):
        zenoh_settings(net, "recorder", "recorder", listen=False)
    assert endpoint(net, "tcp/127.0.0.1:7447") == "tls/127.0.0.1:7447"
    assert endpoint(net, "tls/h:1") == "tls/h:1"
    assert endpoint(paper.network, "tcp/127.0.0.1:7447") == "tcp/127.0.0.1:7447"


def test_identity_arguments_are_checked(paper, lab):
    net = _net(paper, lab, credentials_file="creds.txt")
    with pytest.raises(ValueError, match="role"):
        zenoh_settings(net, "fusion", "fusion", listen=False)
    with pytest.raises(ValueError, match="node id"):
        zenoh_settings(net, "world", "S1", listen=False)
    with pytest.raises(ValueError, match="reserved"):
        zenoh_settings(net, "sensor", "manager", listen=False)


def _allowed(acl: dict, nid: str, flow: str, message: str) -> list[str]:
    """Key expressions the ACL allows ``nid`` for ``message`` in ``flow``."""
    subjects = {s["id"] for s in acl["subjects"] if nid in s.get("usernames", [nid])}
    subjects &= {s["id"] for s in acl["subjects"] if nid in s.get("cert_common_names", [nid])}
    rules = {r["id"]: r for r in acl["rules"]}
    out = []
    for pol in acl["policies"]:
        if subjects & set(pol["subjects"]):
            for rid in pol["rules"]:
                r = rules[rid]
                if flow in r["flows"] and message in r["messages"]:
                    assert r["permission"] == "allow"
                    out += r["key_exprs"]
    return out


def _may(acl: dict, nid: str, flow: str, message: str, key: str) -> bool:
    return any(keyexpr_matches(e, key) for e in _allowed(acl, nid, flow, message))


@pytest.mark.parametrize("identity", ["credentials", "tls", "both"])
def test_access_control_rules(paper, lab, identity):
    sec: dict = {"access_control": True}
    if identity in ("credentials", "both"):
        sec["credentials_file"] = "creds.txt"
    if identity in ("tls", "both"):
        sec["tls"] = {"ca": "pki/ca.pem", "cert_dir": "pki/certs"}
    net = _net(paper, lab, **sec)
    settings = zenoh_settings(net, "manager", "manager", listen=True, sensor_ids=("S1", "S2"))
    acl = settings["access_control"]
    assert acl == access_control(net, ("S1", "S2"))
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    for s in acl["subjects"]:
        assert ("usernames" in s) == (identity != "tls")
        assert ("cert_common_names" in s) == (identity != "credentials")
    assert {s["id"] for s in acl["subjects"]} == {
        "node-world",
        "node-recorder",
        "node-S1",
        "node-S2",
    }
    # ids are unique and every policy names existing rules and subjects
    rules = [r["id"] for r in acl["rules"]]
    assert len(rules) == len(set(rules))
    for pol in acl["policies"]:
        assert set(pol["rules"]) <= set(rules)
    assert all(r["permission"] == "allow" for r in acl["rules"])

    ingress_put = lambda nid, key: _may(acl, nid, "ingress", "put", key)  # noqa: E731
    everyone = ("world", "recorder", "S1", "S2", "manager", "intruder")
    for nid in everyone:  # nobody remote may command, fuse or speak for the manager
        for key in (
            msg.command_key(RUN, ["S1", "S2"]),
            msg.command_key(RUN, []),
            msg.track_key(RUN),
            msg.status_key(RUN),
            msg.heartbeat_key(RUN, "manager", "manager"),
            "other/key",
        ):
            assert not ingress_put(nid, key), (nid, key)
        assert not _may(
            acl, nid, "ingress", "liveliness_token", msg.alive_key(RUN, "manager", "manager")
        )
        assert not _allowed(acl, nid, "ingress", "delete")
        assert not _allowed(acl, nid, "ingress", "declare_queryable")
    assert ingress_put("S1", msg.measurement_key(RUN, "S1"))
    assert ingress_put("S1", msg.heartbeat_key(RUN, "sensor", "S1"))
    assert not ingress_put("S1", msg.measurement_key(RUN, "S2"))
    assert not ingress_put("S1", msg.heartbeat_key(RUN, "sensor", "S2"))
    assert not ingress_put("S1", msg.truth_key(RUN))
    # peer mode: a node publishes its own fused track and status, nobody else's
    assert ingress_put("S1", msg.peer_track_key(RUN, "S1"))
    assert ingress_put("S1", msg.peer_status_key(RUN, "S1"))
    assert not ingress_put("S1", msg.peer_status_key(RUN, "S2"))
    assert not ingress_put("world", msg.peer_track_key(RUN, "S1"))
    assert ingress_put("world", msg.truth_key(RUN))
    assert not ingress_put("world", msg.measurement_key(RUN, "S1"))
    assert ingress_put("recorder", msg.heartbeat_key(RUN, "recorder", "recorder"))
    assert not ingress_put("recorder", msg.truth_key(RUN))
    token = lambda nid, key: _may(acl, nid, "ingress", "liveliness_token", key)  # noqa: E731
    assert token("S1", msg.alive_key(RUN, "sensor", "S1"))
    assert not token("S1", msg.alive_key(RUN, "sensor", "S2"))
    assert token("world", msg.alive_key(RUN, "world", "world"))
    # every known node reads (and subscribes to) every covnet key, an unknown one nothing
    for nid in ("world", "recorder", "S1", "S2"):
        for key in (
            msg.command_key(RUN, ["S1"]),
            msg.truth_key(RUN),
            msg.measurement_key(RUN, "S2"),
        ):
            assert _may(acl, nid, "egress", "put", key)
        assert _allowed(acl, nid, "ingress", "declare_subscriber") == ["covnet/*/**"]
    assert msg.measurement_keyexpr(RUN).startswith("covnet/")
    assert not _allowed(acl, "intruder", "egress", "put")
    # clients get no ACL of their own
    assert "access_control" not in zenoh_settings(net, "sensor", "S1", listen=False)
