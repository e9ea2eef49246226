"""``network.security`` with real zenoh sessions and real processes on 127.0.0.1: access control
(a rogue session's commands never reach a sensor), user/password authentication (a wrong password
cannot join) and mutual TLS (a run over ``tls/`` works; a client without a valid certificate
cannot connect). The CA and the node certificates are generated here with the ``openssl`` CLI,
in a temporary directory (never committed)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from multiproc import REPO, CovnetProcess

from covnet.cli.app import main as covnet_main
from covnet.covariance_control.config import load, normalised
from covnet.processes.launch import EXIT_NO_RUN
from covnet.processes.up import free_port
from covnet.runs.rundir import load_arrays
from covnet.wire import messages as msg
from covnet.wire.security import zenoh_settings
from covnet.wire.zenoh_bus import ZenohBus, zenoh_config

pytestmark = [
    pytest.mark.integration,
    pytest.mark.timeout(120),
    pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl CLI"),
]

SENSORS = ("S1", "S2", "S3")
NODES = (
    "manager",
    "world",
    "recorder",
    *SENSORS,
    "intruder",
)  # intruder: a valid cert/password, no rights
PASSWORDS = {n: f"pw-{n}-{i}" for i, n in enumerate(NODES)}


def _openssl(cwd: Path, *args: str) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=30)


def _make_ca(d: Path, name: str) -> None:
    d.mkdir(parents=True, exist_ok=True)
    _openssl(
        d, "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
        "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", "2", "-subj", f"/CN={name}",
        "-addext", "basicConstraints=critical,CA:TRUE",
        "-addext", "keyUsage=critical,keyCertSign,cRLSign",
    )  # fmt: skip


def _make_cert(ca_dir: Path, out: Path, cn: str) -> None:
    """``out/<cn>.pem`` + ``.key`` signed by ``ca_dir``'s CA: CN = node id, valid for
    127.0.0.1 and localhost, for both TLS server and client use."""
    out.mkdir(parents=True, exist_ok=True)
    ext = out / f"{cn}.ext"
    ext.write_text(
        "basicConstraints=CA:FALSE\nkeyUsage=critical,digitalSignature\n"
        "extendedKeyUsage=serverAuth,clientAuth\nsubjectAltName=DNS:localhost,IP:127.0.0.1\n"
    )
    _openssl(
        out, "req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
        "-keyout", f"{cn}.key", "-out", f"{cn}.csr", "-subj", f"/CN={cn}",
    )  # fmt: skip
    _openssl(
        out, "x509", "-req", "-in", f"{cn}.csr", "-CA", str(ca_dir / "ca.pem"),
        "-CAkey", str(ca_dir / "ca.key"), "-CAcreateserial", "-out", f"{cn}.pem", "-days", "2",
        "-extfile", ext.name,
    )  # fmt: skip


@pytest.fixture(scope="module")
def lab(tmp_path_factory, paper) -> Path:
    """A lab directory: ``pki/`` (CA + every node's certificate), ``rogue-pki/`` (another CA
    that signed a certificate for S1), ``creds.txt``, and config writers."""
    d = tmp_path_factory.mktemp("lab")
    _make_ca(d / "pki", "covnet-test-ca")
    for n in NODES:
        _make_cert(d / "pki", d / "pki" / "certs", n)
    _make_ca(d / "rogue-pki", "rogue-ca")
    _make_cert(d / "rogue-pki", d / "rogue-pki" / "certs", "S1")
    (d / "creds.txt").write_text("".join(f"{n}:{p}\n" for n, p in PASSWORDS.items()))
    return d


def write_config(lab: Path, paper, name: str, record: bool = False, **security) -> Path:
    """A 3-sensor, 20-scan, one-metric variant of the paper scenario with ``security``
    (paths relative to the config file, as a user would write them)."""
    data = normalised(paper)
    data["name"] = name
    data["scans"] = 20
    data["sensors"] = data["sensors"][:3]
    data["allocation"]["metrics"] = ["spectral"]
    data["network"].update(record=record, ready_timeout_s=20.0)
    data["network"]["security"] = security
    path = lab / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def client(sc, ep: str, node: str, role: str = "sensor", **override) -> ZenohBus:
    """A client session with ``node``'s settings from the config (``override`` replaces some)."""
    if node in ("intruder",):
        extra: dict[str, object] = {}
        if sc.network.security.credentials_file:
            extra["transport/auth/usrpwd/user"] = node
            extra["transport/auth/usrpwd/password"] = PASSWORDS[node]
    else:
        extra = zenoh_settings(sc.network, role, node, listen=False)
    extra.update(override)
    return ZenohBus.open(zenoh_config("client", connect=[ep], extra_json5=extra))


def router(sc, ep: str) -> ZenohBus:
    extra = zenoh_settings(sc.network, "manager", "manager", listen=True, sensor_ids=SENSORS)
    return ZenohBus.open(zenoh_config("router", listen=[ep], extra_json5=extra))


def cannot_open(sc, ep: str, node: str, **override) -> str:
    """The error of a client's ``open`` that must fail (fails the test if it opens)."""
    try:
        bus = client(sc, ep, node, **override)
    except Exception as exc:  # zenoh.ZError
        return str(exc)
    bus.close()
    pytest.fail(f"a client as {node!r} with {sorted(override)} opened a session")


class Child:
    """``python -m MODULE ARGS`` in its own process group, output collected."""

    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", *args], cwd=REPO, stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, text=True,
            start_new_session=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )  # fmt: skip
        self.out: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.out.append(line.rstrip("\n"))

    def wait(self, timeout: float) -> int:
        rc = self.proc.wait(timeout=timeout)
        self._close()
        return rc

    def _close(self) -> None:
        self._reader.join(timeout=5)
        if self.proc.stdout is not None and not self._reader.is_alive():
            self.proc.stdout.close()

    def output(self) -> str:
        return "\n".join(self.out)

    def stop(self) -> None:
        for sig in (signal.SIGINT, signal.SIGKILL):
            if self.proc.poll() is not None:
                break
            os.killpg(self.proc.pid, sig)
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                continue
        self.proc.wait()
        self._close()


def drain(sub, kind=None) -> list:
    out = []
    while (s := sub.try_recv()) is not None:
        out.append(s if kind is None else (s.key, msg.decode_as(s.payload, kind)))
    return out


def wait_until(pred, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.02)


def _truth(scan: int) -> msg.Truth:
    return msg.Truth(scan=scan, t=float(scan), target_ids=("T1",), states=np.ones((1, 4)))


def _cmd(scan: int, enabled=SENSORS) -> msg.Command:
    return msg.Command(scan=scan, t=float(scan), enabled=enabled, t_sent_ns=time.monotonic_ns())


def _meas(sensor: str, scan: int) -> msg.Measurement:
    return msg.Measurement(
        sensor_id=sensor, scan=scan, t=float(scan), z=np.zeros((1, 2)), R=np.eye(2),
        t_sent_ns=time.monotonic_ns(),
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# (1) access control: only the manager commands, a sensor publishes only its own keys
# --------------------------------------------------------------------------------------------


def test_access_control_rogue_commands_never_reach_a_sensor(lab, paper):
    """The test holds the router (as the manager does, with the manager's settings); S1 is a real
    sensor process. A compromised S2 (its valid password) and an intruder (a valid password, no
    rights) publish commands, truth and forged S1 measurements: S1 acts on none of them (it
    would measure and publish for scan 7 or 8, and its heartbeats carry the last commanded
    scan), while the manager's command for scan 3 is obeyed."""
    cfg = write_config(lab, paper, "acl", access_control=True, credentials_file="creds.txt")
    sc = load(cfg)
    ep = f"tcp/127.0.0.1:{free_port()}"
    run = msg.new_run_id()
    sensor = None
    with router(sc, ep) as mgr:
        meas = mgr.subscribe(msg.measurement_keyexpr(run))
        hbs = mgr.subscribe(msg.heartbeat_keyexpr(run))
        alive = mgr.watch_liveliness(msg.alive_keyexpr(run))
        mgr_token = mgr.declare_token(msg.alive_key(run, "manager", "manager"))
        seen: list = []
        try:
            sensor = Child("sensors", "--config", str(cfg), "--id", "S1", "--run", run,
                           "--connect", ep)  # fmt: skip

            def s1_alive() -> bool:
                while (ev := alive.try_recv()) is not None:
                    seen.append(ev)
                return any(e.alive and e.key.endswith("/sensor/S1") for e in seen)

            wait_until(s1_alive, 30, "S1's liveliness token")
            with client(sc, ep, "S2") as rogue, client(sc, ep, "intruder") as intruder:
                eavesdrop = intruder.subscribe(f"covnet/{run}/**")
                rogue_token = rogue.declare_token(msg.alive_key(run, "sensor", "S3"))
                own_token = rogue.declare_token(msg.alive_key(run, "sensor", "S2"))
                # positive control first: the rogue session is up and may publish its own key
                got: list = []
                wait_until(
                    lambda: (
                        rogue.publish(msg.measurement_key(run, "S2"), msg.encode(_meas("S2", 7)))
                        or got.extend(drain(meas, msg.Measurement))
                        or got
                    ),
                    10,
                    "S2's measurement on its own key",
                )
                # truth for the rogue scans comes from the router itself: had a rogue command
                # got through, S1 would have had what it needs to measure
                mgr.publish(msg.truth_key(run), msg.encode(_truth(7)))
                mgr.publish(msg.truth_key(run), msg.encode(_truth(8)))
                for _ in range(5):
                    rogue.publish(msg.command_key(run, SENSORS), msg.encode(_cmd(7)))
                    rogue.publish(msg.truth_key(run), msg.encode(_truth(7)))
                    rogue.publish(msg.measurement_key(run, "S1"), msg.encode(_meas("S1", 7)))
                    intruder.publish(msg.command_key(run, SENSORS), msg.encode(_cmd(8)))
                    intruder.publish(msg.measurement_key(run, "S1"), msg.encode(_meas("S1", 8)))
                    time.sleep(0.02)
                time.sleep(0.5)  # time for anything that slipped through to act
                # the manager's command for scan 3 arrives and is obeyed
                mgr.publish(msg.truth_key(run), msg.encode(_truth(3)))
                mgr.publish(msg.command_key(run, ("S1",)), msg.encode(_cmd(3, ("S1",))))
                wait_until(
                    lambda: (
                        got.extend(drain(meas, msg.Measurement))
                        or any(m.sensor_id == "S1" for _, m in got)
                    ),
                    10,
                    "S1's measurement for the manager's command",
                )
                beats: list = []
                wait_until(
                    lambda: (
                        beats.extend(drain(hbs, msg.Heartbeat))
                        or any(h.node_id == "S1" and h.scan == 3 for _, h in beats)
                    ),
                    10,
                    "S1's heartbeat after scan 3",
                )
                got.extend(drain(meas, msg.Measurement))
                s1_alive()
                heard = drain(eavesdrop)
                rogue_token.undeclare()
                own_token.undeclare()
            assert {(k, m.sensor_id, m.scan) for k, m in got} == {
                (msg.measurement_key(run, "S2"), "S2", 7),
                (msg.measurement_key(run, "S1"), "S1", 3),
            }
            assert sum(m.sensor_id == "S1" for _, m in got) == 1
            assert {h.scan for _, h in beats if h.node_id == "S1"} <= {0, 3}
            assert not any(h.rejected for _, h in beats if h.node_id == "S1")
            alive_keys = {e.key for e in seen if e.alive}
            assert msg.alive_key(run, "sensor", "S2") in alive_keys
            assert msg.alive_key(run, "sensor", "S3") not in alive_keys
            # the intruder hears only its own puts (a session hears itself), nothing routed
            assert heard and all(msg.decode(h.payload).scan == 8 for h in heard), heard
            # the run ends as a manager ends it (its end declared, then its token gone): the
            # sensor stops on its own, and its own token's disappearance goes through the ACL
            mgr.declare_token(msg.done_key(run))
            mgr_token.undeclare()
            assert sensor.wait(timeout=15) == 0, sensor.output()
            wait_until(
                lambda: (
                    s1_alive() and any(not e.alive and e.key.endswith("/sensor/S1") for e in seen)
                ),
                10,
                "S1's token to go",
            )
            assert "1 scans enabled, 1 measurements sent, rejected {}" in sensor.output()
        finally:
            if sensor is not None:
                sensor.stop()


# --------------------------------------------------------------------------------------------
# (2) user/password authentication
# --------------------------------------------------------------------------------------------


def test_wrong_password_cannot_join(lab, paper):
    """A client with a wrong password, an unknown user or no credentials at all cannot open a
    session: ``zenoh.open`` fails at once ("Unable to connect"). A node process given a wrong
    password retries until ``ready_timeout_s`` and exits 4 (``EXIT_NO_RUN``: not restarted)."""
    cfg = write_config(lab, paper, "pw", credentials_file="creds.txt")
    sc = load(cfg)
    ep = f"tcp/127.0.0.1:{free_port()}"
    wrong = lab / "wrong-creds.txt"
    wrong.write_text("".join(f"{n}:{p}-wrong\n" for n, p in PASSWORDS.items()))
    bad_cfg = write_config(lab, paper, "pw-wrong", credentials_file=wrong.name)
    data = yaml.safe_load(bad_cfg.read_text())
    data["network"]["ready_timeout_s"] = 1.0
    bad_cfg.write_text(yaml.safe_dump(data, sort_keys=False))
    with router(sc, ep):
        with client(sc, ep, "S1") as ok:  # positive control
            ok.publish(msg.heartbeat_key("r", "sensor", "S1"), b"x")
        user, pw = "transport/auth/usrpwd/user", "transport/auth/usrpwd/password"
        t0 = time.monotonic()
        err = cannot_open(sc, ep, "S1", **{pw: "not-the-password"})
        assert "Unable to connect" in err
        assert time.monotonic() - t0 < 5
        cannot_open(sc, ep, "S1", **{user: "nobody", pw: "x"})
        cannot_open(sc, ep, "S1", **{user: None, pw: None})
        child = Child("sensors", "--config", str(bad_cfg), "--id", "S2", "--run", "r",
                      "--connect", ep)  # fmt: skip
        try:
            assert child.wait(timeout=30) == EXIT_NO_RUN
        finally:
            child.stop()
        assert "cannot open a zenoh client session" in child.output()


# --------------------------------------------------------------------------------------------
# (3) mutual TLS
# --------------------------------------------------------------------------------------------


def test_client_without_a_valid_certificate_cannot_connect(lab, paper):
    cfg = write_config(
        lab, paper, "tls-only", tls={"ca": "pki/ca.pem", "cert_dir": "pki/certs"},
        access_control=True,
    )  # fmt: skip
    sc = load(cfg)
    ep = f"tls/127.0.0.1:{free_port()}"
    tls = "transport/link/tls/"
    rogue = lab / "rogue-pki"
    with router(sc, ep) as mgr:
        with client(sc, ep, "S1") as ok:  # positive control
            sub = ok.subscribe(msg.command_keyexpr("r", "S1"))
            wait_until(
                lambda: mgr.publish(msg.command_key("r", ["S1"]), b"hello") or sub.recv(0.1),
                10,
                "S1",
            )
        # no client certificate (and not even mTLS on the client side)
        cannot_open(sc, ep, "S1", **{
            tls + "connect_certificate": None, tls + "connect_private_key": None,
            tls + "enable_mtls": False,
        })  # fmt: skip
        # a certificate for CN=S1 signed by another CA
        cannot_open(sc, ep, "S1", **{
            tls + "connect_certificate": str(rogue / "certs" / "S1.pem"),
            tls + "connect_private_key": str(rogue / "certs" / "S1.key"),
        })  # fmt: skip
        # a router the client does not trust (the client checks the router's certificate)
        cannot_open(sc, ep, "S1", **{tls + "root_ca_certificate": str(rogue / "ca.pem")})
        # plain TCP to the TLS port
        with pytest.raises(Exception, match="Unable to connect"):
            ZenohBus.open(zenoh_config("client", connect=[ep.replace("tls/", "tcp/")])).close()
        # a valid certificate whose common name has no rights: it connects, but nothing it
        # publishes reaches anyone and it receives nothing
        with client(sc, ep, "intruder", **{
            tls + "root_ca_certificate": sc.network.security.tls.ca,
            tls + "connect_certificate": str(lab / "pki" / "certs" / "intruder.pem"),
            tls + "connect_private_key": str(lab / "pki" / "certs" / "intruder.key"),
            tls + "enable_mtls": True,
        }) as intruder:  # fmt: skip
            heard = intruder.subscribe("covnet/**")
            mine = mgr.subscribe("covnet/**")
            time.sleep(0.2)
            intruder.publish(msg.command_key("r", ["S1"]), b"rogue")
            mgr.publish(msg.command_key("r", ["S1"]), b"manager")
            assert mine.recv(5).payload == b"manager"
            time.sleep(0.3)
            assert mine.try_recv() is None  # the intruder's command was dropped
            # it hears only its own put (a session hears itself), nothing from the router
            assert [h.payload for h in drain(heard)] == [b"rogue"]


def test_up_over_mutual_tls_with_access_control(lab, paper, tmp_path):
    """``covnet up`` with mutual TLS, passwords and access control (and the recorder): the
    router listens on ``tls/127.0.0.1:<free port>`` and the run equals the in-process one."""
    cfg = write_config(
        lab, paper, "tls", record=True,
        access_control=True,
        credentials_file="creds.txt",
        tls={"ca": "pki/ca.pem", "cert_dir": "pki/certs"},
    )  # fmt: skip
    ref = tmp_path / "ref"
    assert covnet_main(["run", str(cfg), "--out", str(ref), "--no-figures"]) == 0
    out = tmp_path / "up"
    p = CovnetProcess(["up", str(cfg), "--out", str(out), "--no-figures"])
    try:
        rc = p.wait(timeout=90)
    finally:
        p.stop()
    assert rc == 0, p.output()
    assert "router tls/127.0.0.1:" in p.output()
    assert (out / "recording.mcap").stat().st_size > 0
    want = json.loads((ref / "summary.json").read_text())["metrics"]["spectral"]
    got = json.loads((out / "summary.json").read_text())["metrics"]["spectral"]
    assert got["subsets"] == want["subsets"]
    a_ref, a_got = load_arrays(ref / "arrays.npz"), load_arrays(out / "arrays.npz")
    np.testing.assert_allclose(a_got["x_est.spectral"], a_ref["x_est.spectral"], atol=1e-12)
    net = json.loads((out / "network.json").read_text())
    assert net["rejected"] == {} and net["lost"] == 0
    for sid in SENSORS:
        received = sum(
            v["messages"] for k, v in net["received"].items() if k.endswith(f"/sensor/{sid}/meas")
        )
        assert received == got["usage"][sid], sid


def test_up_checks_keys_and_passwords_before_starting_anything(lab, paper, tmp_path, capsys):
    certs = tmp_path / "certs"
    shutil.copytree(lab / "pki" / "certs", certs)
    (certs / "S2.key").unlink()
    cfg = write_config(
        lab, paper, "tls-missing-key",
        credentials_file="creds.txt",
        tls={"ca": "pki/ca.pem", "cert_dir": str(certs)},
    )  # fmt: skip
    out = tmp_path / "up"
    assert covnet_main(["up", str(cfg), "--out", str(out), "--no-figures"]) == 2
    err = capsys.readouterr().err
    assert "network.security.tls.cert_dir" in err and "S2.key" in err
    assert not (out / "processes.json").exists()
