"""A node that the router refuses says so in covnet's words: a real router (the manager's
settings, in this process) and a real sensor process (``python -m sensors``) given a wrong
password, or a certificate from another CA. The sensor exits 1 within a few seconds (not at
``ready_timeout_s``) and its stderr names the node and the cause, zenoh's own message after it
in parentheses; a router that is simply not there is not called an authentication failure."""

from __future__ import annotations

import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from multiproc import REPO
from test_security import PASSWORDS, _make_ca, _make_cert, client, router, write_config

from covnet.covariance_control.config import load
from covnet.processes.launch import EXIT_NO_RUN
from covnet.processes.up import free_port
from covnet.wire import messages as msg

pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl CLI"),
]

READY_TIMEOUT_S = 30.0  # what the sensor would wait for a router that is not there


@pytest.fixture(scope="module")
def lab(tmp_path_factory) -> Path:
    """``pki/`` (a CA and every node's certificate), ``rogue-pki/`` (another CA that signed a
    certificate for S1), ``creds.txt`` and ``wrong-creds.txt`` (every password wrong)."""
    d = tmp_path_factory.mktemp("login")
    _make_ca(d / "pki", "covnet-test-ca")
    for n in ("manager", "world", "S1"):
        _make_cert(d / "pki", d / "pki" / "certs", n)
    _make_ca(d / "rogue-pki", "rogue-ca")
    _make_cert(d / "rogue-pki", d / "rogue-pki" / "certs", "S1")
    (d / "creds.txt").write_text("".join(f"{n}:{p}\n" for n, p in PASSWORDS.items()))
    (d / "wrong-creds.txt").write_text("".join(f"{n}:{p}-wrong\n" for n, p in PASSWORDS.items()))
    return d


def _config(lab: Path, paper, name: str, **security) -> Path:
    path = write_config(lab, paper, name, **security)
    data = yaml.safe_load(path.read_text())
    data["network"]["ready_timeout_s"] = READY_TIMEOUT_S
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def sensor(cfg: Path, ep: str, node: str = "S1") -> tuple[int, str, float]:
    """``python -m sensors`` as ``node`` against ``ep``: (exit status, stderr, seconds)."""
    t0 = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-m", "sensors", "--config", str(cfg), "--id", node, "--run", "r",
         "--connect", ep],
        cwd=REPO, capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL,
    )  # fmt: skip
    return done.returncode, done.stderr, time.monotonic() - t0


@pytest.mark.timeout(120)
def test_wrong_password_says_authentication_failed(lab, paper):
    good = load(_config(lab, paper, "login-ok", credentials_file="creds.txt"))
    wrong = _config(lab, paper, "login-wrong", credentials_file="wrong-creds.txt")
    ep = f"tcp/127.0.0.1:{free_port()}"
    with router(good, ep):
        with client(good, ep, "S1") as ok:  # positive control: the right password opens
            ok.publish(msg.heartbeat_key("r", "sensor", "S1"), b"x")
        rc, err, took = sensor(wrong, ep)
    assert rc == EXIT_NO_RUN, err  # not restarted: no run to join
    line = next(ln for ln in err.splitlines() if "authentication failed for S1" in ln)
    assert line.startswith("sensors: error: authentication failed for S1 (the password in ")
    assert f"{lab / 'wrong-creds.txt'} is not the router's" in line
    assert "or the router does not accept user S1)" in line
    assert "cannot open a zenoh client session" in line
    assert "(zenoh: Unable to connect to any of" in line  # zenoh's text, kept for debugging
    assert took < READY_TIMEOUT_S / 2, took  # told when the router refuses, not at the timeout


@pytest.mark.timeout(120)
def test_certificate_of_another_ca_says_tls_handshake_failed(lab, paper):
    tls = {"ca": "pki/ca.pem", "cert_dir": "pki/certs"}
    good = load(_config(lab, paper, "tls-ok", tls=tls))
    rogue = _config(lab, paper, "tls-rogue", tls={**tls, "cert_dir": "rogue-pki/certs"})
    ep = f"tls/127.0.0.1:{free_port()}"
    with router(good, ep):
        with client(good, ep, "S1"):  # positive control: S1's own certificate opens
            pass
        rc, err, took = sensor(rogue, ep)
    assert rc == EXIT_NO_RUN, err  # not restarted: no run to join
    line = next(ln for ln in err.splitlines() if "TLS handshake failed for S1" in ln)
    assert "the router rejected S1's certificate" in line
    assert str(lab / "rogue-pki" / "certs" / "S1.pem") in line
    assert "(zenoh: Unable to connect to any of" in line
    assert took < READY_TIMEOUT_S / 2, took


@pytest.mark.timeout(120)
def test_no_router_is_not_an_authentication_failure(lab, paper):
    """Nothing listens: the sensor waits ``ready_timeout_s`` and reports zenoh's error."""
    cfg = _config(lab, paper, "login-none", credentials_file="creds.txt")
    data = yaml.safe_load(cfg.read_text())
    data["network"]["ready_timeout_s"] = 1.0
    cfg.write_text(yaml.safe_dump(data, sort_keys=False))
    rc, err, _ = sensor(cfg, f"tcp/127.0.0.1:{free_port()}")
    assert rc == EXIT_NO_RUN, err  # not restarted: no run to join
    assert "cannot open a zenoh client session" in err
    assert "authentication failed" not in err and "TLS handshake failed" not in err
