"""``covnet check`` / :func:`covnet.wire.security.preflight` check the TLS certificates as zenoh
(rustls, webpki) will use them, and :func:`covnet.wire.security.login_problem` tells why a router
refuses a client, without zenoh.

The certificates are made here with the ``cryptography`` API, in a temporary directory: a CA
and node certificates like the integration tests' (X.509 v3, CA:FALSE, keyUsage
digitalSignature, extendedKeyUsage serverAuth+clientAuth, subjectAltName DNS:localhost and
IP:127.0.0.1), then one thing broken at a time. What zenoh 1.10 itself refuses was measured
with real sessions: v1, expired or not yet valid, another CA (or another CA's key under the same
name), CA:TRUE on a node, an extendedKeyUsage without the needed purpose, a key that does not
match or is encrypted, a 1024-bit RSA or a P-521 key, ECDSA with SHA-512, and (verify_name) a
router certificate whose subjectAltName does not name the connect host; a node certificate
without keyUsage, extendedKeyUsage, basicConstraints or subjectAltName works, and so does one
whose keyUsage lacks digitalSignature (reported anyway: RFC 5280 forbids signing with it).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import re
import socket
import struct
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import yaml
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec, ed25519, rsa
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from covnet.cli.app import main as covnet_main
from covnet.config import ConfigError
from covnet.covariance_control.config import load, normalised
from covnet.wire.security import certificate_problems, login_problem, preflight

NOW = dt.datetime.now(dt.UTC)
NODES = ("manager", "world", "recorder", "S1", "S2")  # what covnet check checks
CERT_DIR = "network.security.tls.cert_dir"
CA_FIELD = "network.security.tls.ca"

# --------------------------------------------------------------------------------------------
# a small PKI
# --------------------------------------------------------------------------------------------

Key = ec.EllipticCurvePrivateKey | rsa.RSAPrivateKey | ed25519.Ed25519PrivateKey


def _name(cn: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])


def _write_key(key: Key, path: Path, password: bytes | None = None) -> None:
    enc: serialization.KeySerializationEncryption = (
        serialization.BestAvailableEncryption(password)
        if password
        else serialization.NoEncryption()
    )
    path.write_bytes(
        key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, enc)
    )


def _pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def _usage(**on: bool) -> x509.KeyUsage:
    flags = dict.fromkeys(
        (
            "digital_signature",
            "content_commitment",
            "key_encipherment",
            "data_encipherment",
            "key_agreement",
            "key_cert_sign",
            "crl_sign",
            "encipher_only",
            "decipher_only",
        ),
        False,
    )
    return x509.KeyUsage(**{**flags, **on})


DIGITAL_SIGNATURE = _usage(digital_signature=True)


def _der(buf: bytes, i: int) -> tuple[int, bytes, int]:
    """(tag, body, end) of the DER element at ``buf[i]``."""
    tag, n, j = buf[i], buf[i + 1], i + 2
    if n & 0x80:
        m = n & 0x7F
        n, j = int.from_bytes(buf[j : j + m], "big"), j + m
    return tag, buf[j : j + n], j + n


def _tlv(tag: int, body: bytes) -> bytes:
    n = len(body)
    size = bytes([n]) if n < 0x80 else bytes([0x80 | ((n.bit_length() + 7) // 8)])
    if n >= 0x80:
        size += n.to_bytes((n.bit_length() + 7) // 8, "big")
    return bytes([tag]) + size + body


def to_v1(cert: x509.Certificate, signer: ec.EllipticCurvePrivateKey) -> x509.Certificate:
    """``cert`` as X.509 v1 (what ``openssl x509 -req`` without ``-extfile`` makes): the
    version field and the extensions dropped, signed again (ECDSA with SHA-256)."""
    der = cert.public_bytes(serialization.Encoding.DER)
    _, outer, _ = _der(der, 0)
    _, tbs, end = _der(outer, 0)
    _, alg, _ = _der(outer, end)
    fields, i = [], 0
    while i < len(tbs):
        tag, _, j = _der(tbs, i)
        if tag not in (0xA0, 0xA3):  # [0] version, [3] extensions
            fields.append(tbs[i:j])
        i = j
    new_tbs = _tlv(0x30, b"".join(fields))
    sig = signer.sign(new_tbs, ec.ECDSA(hashes.SHA256()))
    out = x509.load_der_x509_certificate(
        _tlv(0x30, new_tbs + _tlv(0x30, alg) + _tlv(0x03, b"\x00" + sig))
    )
    assert out.version == x509.Version.v1
    return out


class CA:
    """A CA certificate and its key (``dir/ca.pem``, ``dir/ca.key``)."""

    def __init__(
        self,
        d: Path,
        cn: str = "covnet-test-ca",
        *,
        is_ca: bool | None = True,
        key_usage: x509.KeyUsage | None = None,
        days: tuple[float, float] = (-1, 2),
        v1: bool = False,
    ) -> None:
        self.key = ec.generate_private_key(ec.SECP256R1())
        b = (
            x509.CertificateBuilder()
            .subject_name(_name(cn))
            .issuer_name(_name(cn))
            .public_key(self.key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(NOW + dt.timedelta(days=days[0]))
            .not_valid_after(NOW + dt.timedelta(days=days[1]))
        )
        if is_ca is not None:
            b = b.add_extension(x509.BasicConstraints(ca=is_ca, path_length=None), critical=True)
        b = b.add_extension(key_usage or _usage(key_cert_sign=True, crl_sign=True), critical=True)
        self.cert = b.sign(self.key, hashes.SHA256())
        if v1:
            self.cert = to_v1(self.cert, self.key)
        d.mkdir(parents=True, exist_ok=True)
        (d / "ca.pem").write_bytes(_pem(self.cert))
        _write_key(self.key, d / "ca.key")
        self.path = d / "ca.pem"

    def issue(
        self,
        out: Path,
        cn: str,
        *,
        file: str | None = None,
        key: Key | None = None,
        days: tuple[float, float] = (-1, 2),
        is_ca: bool | None = False,
        key_usage: x509.KeyUsage | None = DIGITAL_SIGNATURE,
        eku: tuple[x509.ObjectIdentifier, ...] | None = (
            ExtendedKeyUsageOID.SERVER_AUTH,
            ExtendedKeyUsageOID.CLIENT_AUTH,
        ),
        san: tuple[str, ...] | None = ("localhost", "127.0.0.1"),
        v1: bool = False,
        digest: hashes.HashAlgorithm | None = None,
        chain: tuple[x509.Certificate, ...] = (),
    ) -> x509.Certificate:
        """``out/<file or cn>.pem`` + ``.key``: a node certificate with common name ``cn``,
        signed by this CA (``chain`` certificates follow it in the file)."""
        key = key or ec.generate_private_key(ec.SECP256R1())
        b = (
            x509.CertificateBuilder()
            .subject_name(_name(cn))
            .issuer_name(self.cert.subject)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(NOW + dt.timedelta(days=days[0]))
            .not_valid_after(NOW + dt.timedelta(days=days[1]))
        )
        if is_ca is not None:
            b = b.add_extension(x509.BasicConstraints(ca=is_ca, path_length=None), critical=True)
        if key_usage is not None:
            b = b.add_extension(key_usage, critical=True)
        if eku is not None:
            b = b.add_extension(x509.ExtendedKeyUsage(list(eku)), critical=False)
        if san is not None:
            names: list[x509.GeneralName] = []
            for s in san:
                try:
                    names.append(x509.IPAddress(ipaddress.ip_address(s)))
                except ValueError:
                    names.append(x509.DNSName(s))
            b = b.add_extension(x509.SubjectAlternativeName(names), critical=False)
        cert = b.sign(self.key, digest or hashes.SHA256())
        if v1:
            cert = to_v1(cert, self.key)
        out.mkdir(parents=True, exist_ok=True)
        (out / f"{file or cn}.pem").write_bytes(_pem(cert) + b"".join(_pem(c) for c in chain))
        _write_key(key, out / f"{file or cn}.key")
        return cert


@pytest.fixture()
def lab(tmp_path: Path) -> Path:
    """``pki/ca.pem`` and a good certificate for every node in ``pki/certs``."""
    ca = CA(tmp_path / "pki")
    for n in NODES:
        ca.issue(tmp_path / "pki" / "certs", n)
    return tmp_path


def _ca(lab: Path) -> CA:
    """A CA object for the lab's CA (its key read back), to issue more certificates."""
    ca = CA.__new__(CA)
    ca.path = lab / "pki" / "ca.pem"
    ca.cert = x509.load_pem_x509_certificate(ca.path.read_bytes())
    key = serialization.load_pem_private_key((lab / "pki" / "ca.key").read_bytes(), None)
    assert isinstance(key, ec.EllipticCurvePrivateKey)
    ca.key = key
    return ca


def write_config(lab: Path, paper, *, verify_name: bool = True, **network) -> Path:
    """A 2-sensor paper config with mutual TLS (paths relative to the config file)."""
    data = normalised(paper)
    data["sensors"] = data["sensors"][:2]
    data["network"]["record"] = False
    data["network"].update(network)
    data["network"]["security"] = {
        "tls": {"ca": "pki/ca.pem", "cert_dir": "pki/certs", "verify_name": verify_name}
    }
    path = lab / "lab.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def problems_of(cfg: Path) -> list[tuple[str, str]]:
    try:
        preflight(load(cfg), NODES, str(cfg))
    except ConfigError as exc:
        return exc.problems
    return []


def check(cfg: Path, capsys) -> tuple[int, str]:
    rc = covnet_main(["check", str(cfg)])
    return rc, capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# the good set, and what zenoh accepts
# --------------------------------------------------------------------------------------------


def test_good_certificates_pass(lab, paper, capsys):
    cfg = write_config(lab, paper)
    assert problems_of(cfg) == []
    rc, err = check(cfg, capsys)
    assert rc == 0, err


def test_what_zenoh_accepts_passes(lab, paper):
    """No optional extension on the clients (no keyUsage, extendedKeyUsage, basicConstraints,
    subjectAltName), other key types zenoh takes, an intermediate CA in the node's file, a
    router certificate only for the connect host by a wildcard name."""
    ca, certs = _ca(lab), lab / "pki" / "certs"
    ca.issue(certs, "world", key_usage=None, eku=None, is_ca=None, san=None)
    ca.issue(certs, "recorder", key=rsa.generate_private_key(65537, 2048))
    ca.issue(certs, "S1", key=ed25519.Ed25519PrivateKey.generate(), digest=None)
    mid = CA(lab / "mid", "covnet-intermediate")
    mid_cert = (
        x509.CertificateBuilder()
        .subject_name(mid.cert.subject)
        .issuer_name(ca.cert.subject)
        .public_key(mid.key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(NOW - dt.timedelta(days=1))
        .not_valid_after(NOW + dt.timedelta(days=2))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .sign(ca.key, hashes.SHA256())
    )
    mid.issue(certs, "S2", key=ec.generate_private_key(ec.SECP384R1()), chain=(mid_cert,))
    ca.issue(certs, "manager", san=("*.lab",), eku=(ExtendedKeyUsageOID.SERVER_AUTH,))
    assert problems_of(write_config(lab, paper, connect="tcp/manager.lab:7447")) == []


def test_verify_name_off_needs_no_subject_alt_name(lab, paper):
    _ca(lab).issue(lab / "pki" / "certs", "manager", san=None)
    assert problems_of(write_config(lab, paper, verify_name=False)) == []
    [(path, message)] = problems_of(write_config(lab, paper))
    assert path == CERT_DIR and "manager's certificate" in message


# --------------------------------------------------------------------------------------------
# one thing wrong at a time: exactly that problem, naming the node (or the CA) and the file
# --------------------------------------------------------------------------------------------


def _v1(lab: Path) -> None:
    _ca(lab).issue(lab / "pki" / "certs", "S1", v1=True)


def _expired(lab: Path) -> None:
    _ca(lab).issue(lab / "pki" / "certs", "S2", days=(-10, -3))


def _not_yet_valid(lab: Path) -> None:
    _ca(lab).issue(lab / "pki" / "certs", "world", days=(3, 10))


def _cn_of_another_node(lab: Path) -> None:
    _ca(lab).issue(lab / "pki" / "certs", "S1", file="S2")


def _other_ca(lab: Path) -> None:
    CA(lab / "rogue", "rogue-ca").issue(lab / "pki" / "certs", "S1")


def _other_ca_same_name(lab: Path) -> None:
    CA(lab / "rogue", "covnet-test-ca").issue(lab / "pki" / "certs", "S1")


def _key_mismatch(lab: Path) -> None:
    _write_key(ec.generate_private_key(ec.SECP256R1()), lab / "pki" / "certs" / "recorder.key")


def _encrypted_key(lab: Path) -> None:
    path = lab / "pki" / "certs" / "S2.key"
    key = serialization.load_pem_private_key(path.read_bytes(), None)
    assert isinstance(key, ec.EllipticCurvePrivateKey)
    _write_key(key, path, password=b"secret")


def _missing_key(lab: Path) -> None:
    (lab / "pki" / "certs" / "S2.key").unlink()


def _not_a_certificate(lab: Path) -> None:
    (lab / "pki" / "certs" / "S1.pem").write_text(
        "-----BEGIN CERTIFICATE-----\nAAAA\n-----END CERTIFICATE-----\n"
    )


def _manager_without_san(lab: Path) -> None:
    _ca(lab).issue(lab / "pki" / "certs", "manager", san=None)


def _manager_dns_only(lab: Path) -> None:
    _ca(lab).issue(lab / "pki" / "certs", "manager", san=("localhost",))


def _node_is_a_ca(lab: Path) -> None:
    _ca(lab).issue(lab / "pki" / "certs", "S1", is_ca=True)


def _client_server_only(lab: Path) -> None:
    _ca(lab).issue(lab / "pki" / "certs", "world", eku=(ExtendedKeyUsageOID.SERVER_AUTH,))


def _router_client_only(lab: Path) -> None:
    _ca(lab).issue(lab / "pki" / "certs", "manager", eku=(ExtendedKeyUsageOID.CLIENT_AUTH,))


def _no_digital_signature(lab: Path) -> None:
    _ca(lab).issue(lab / "pki" / "certs", "S1", key_usage=_usage(key_encipherment=True))


def _rsa_1024(lab: Path) -> None:
    _ca(lab).issue(lab / "pki" / "certs", "S2", key=rsa.generate_private_key(65537, 1024))


def _p521(lab: Path) -> None:
    _ca(lab).issue(lab / "pki" / "certs", "S2", key=ec.generate_private_key(ec.SECP521R1()))


def _sha512(lab: Path) -> None:
    _ca(lab).issue(lab / "pki" / "certs", "S1", digest=hashes.SHA512())


def _reissue_all(lab: Path, **ca_options) -> None:
    """A new CA (with ``ca_options``) and every node certificate issued by it."""
    ca = CA(lab / "pki", **ca_options)
    for n in NODES:
        ca.issue(lab / "pki" / "certs", n)


CASES: list[tuple[str, Callable[[Path], None], str, list[str]]] = [
    ("v1", _v1, CERT_DIR, ["S1's certificate", "S1.pem", "is X.509 v1", "only v3"]),
    ("expired", _expired, CERT_DIR, ["S2's certificate", "S2.pem", "expired on", "valid from"]),
    ("not-yet-valid", _not_yet_valid, CERT_DIR, ["world's certificate", "is not valid yet"]),
    (
        "cn-of-another-node",
        _cn_of_another_node,
        CERT_DIR,
        ["S2's certificate", "S2.pem", "has common name 'S1'; expected 'S2'"],
    ),
    (
        "other-ca",
        _other_ca,
        CERT_DIR,
        ["S1's certificate", "is not signed by the CA", "ca.pem", "issuer is 'CN=rogue-ca'"],
    ),
    (
        "other-ca-same-name",
        _other_ca_same_name,
        CERT_DIR,
        ["S1's certificate", "did not sign it", "another CA of the same name"],
    ),
    (
        "key-mismatch",
        _key_mismatch,
        CERT_DIR,
        ["recorder's private key", "recorder.key", "does not match", "recorder.pem"],
    ),
    ("encrypted-key", _encrypted_key, CERT_DIR, ["S2's private key", "S2.key", "is encrypted"]),
    ("missing-key", _missing_key, CERT_DIR, ["S2's private key", "S2.key", "does not exist"]),
    (
        "not-a-certificate",
        _not_a_certificate,
        CERT_DIR,
        ["S1's certificate", "S1.pem", "is not a valid PEM certificate"],
    ),
    (
        "manager-without-san",
        _manager_without_san,
        CERT_DIR,
        ["manager's certificate", "has no subjectAltName", "127.0.0.1", "IP:127.0.0.1"],
    ),
    (
        "manager-dns-only",
        _manager_dns_only,
        CERT_DIR,
        ["manager's certificate", "names DNS:localhost but not 127.0.0.1", "IP:127.0.0.1"],
    ),
    ("node-is-a-ca", _node_is_a_ca, CERT_DIR, ["S1's certificate", "CA:TRUE", "CA:FALSE"]),
    (
        "client-without-clientAuth",
        _client_server_only,
        CERT_DIR,
        ["world's certificate", "extendedKeyUsage serverAuth without clientAuth"],
    ),
    (
        "router-without-serverAuth",
        _router_client_only,
        CERT_DIR,
        ["manager's certificate", "extendedKeyUsage clientAuth without serverAuth"],
    ),
    (
        "no-digitalSignature",
        _no_digital_signature,
        CERT_DIR,
        ["S1's certificate", "keyUsage keyEncipherment without digitalSignature"],
    ),
    ("rsa-1024", _rsa_1024, CERT_DIR, ["S2's certificate", "1024-bit RSA key", "2048 to 8192"]),
    ("p-521", _p521, CERT_DIR, ["S2's certificate", "secp521r1", "P-256 or P-384"]),
    ("sha-512", _sha512, CERT_DIR, ["S1's certificate", "ECDSA and SHA512", "SHA-256"]),
    (
        "ca-without-ca-true",
        lambda lab: _reissue_all(lab, is_ca=False),
        CA_FIELD,
        ["the CA certificate", "ca.pem", "basicConstraints CA:FALSE", "expected CA:TRUE"],
    ),
    (
        "ca-without-basic-constraints",
        lambda lab: _reissue_all(lab, is_ca=None),
        CA_FIELD,
        ["the CA certificate", "no basicConstraints", "CA:TRUE"],
    ),
    (
        "ca-without-keyCertSign",
        lambda lab: _reissue_all(lab, key_usage=_usage(digital_signature=True)),
        CA_FIELD,
        ["the CA certificate", "keyUsage digitalSignature without keyCertSign"],
    ),
    (
        "ca-v1",
        lambda lab: _reissue_all(lab, v1=True),
        CA_FIELD,
        ["the CA certificate", "is X.509 v1"],
    ),
    (
        "ca-expired",
        lambda lab: _reissue_all(lab, days=(-10, -3)),
        CA_FIELD,
        ["the CA certificate", "expired on"],
    ),
]


def _timeless(text: str) -> str:
    """``text`` without the clock readings (``now 2026-12-02 04:23:05 UTC``): the check runs
    twice, and the second may read the next second."""
    return re.sub(r"now \d{4}-\d\d-\d\d \d\d:\d\d:\d\d UTC", "now <time>", text)


@pytest.mark.parametrize(
    "break_it, path, fragments", [c[1:] for c in CASES], ids=[c[0] for c in CASES]
)
def test_one_problem_reported_exactly(lab, paper, capsys, break_it, path, fragments):
    break_it(lab)
    cfg = write_config(lab, paper, record=True)  # (check then asks for the recorder's files)
    problems = problems_of(cfg)
    assert len(problems) == 1, problems
    [(got_path, message)] = problems
    assert got_path == path
    for fragment in fragments:
        assert fragment in message, (fragment, message)
    rc, err = check(cfg, capsys)
    assert rc == 2
    assert _timeless(f"{path}: {message}") in _timeless(err)
    assert "invalid config" in err and str(cfg) in err


def test_every_problem_at_once(lab, paper, capsys):
    for break_it in (_v1, _expired, _not_yet_valid, _manager_without_san, _key_mismatch):
        break_it(lab)
    cfg = write_config(lab, paper, record=True)  # (check then asks for the recorder's files)
    problems = problems_of(cfg)
    who = sorted(m.split("'s ")[0] for _, m in problems)
    assert who == ["S1", "S2", "manager", "recorder", "world"], problems
    rc, err = check(cfg, capsys)
    assert rc == 2 and all(_timeless(m) in _timeless(err) for _, m in problems)


def test_only_the_nodes_of_this_host(lab, paper):
    """``covnet up --nodes S1`` checks S1's files (and the CA) only."""
    _expired(lab)  # S2's
    (lab / "pki" / "certs" / "manager.pem").unlink()
    sc = load(write_config(lab, paper))
    assert certificate_problems(sc.network, ["S1"]) == []
    assert [m.split("'s ")[0] for _, m in certificate_problems(sc.network, ["S1", "S2"])] == ["S2"]


def test_the_connect_host_is_the_one_checked(lab, paper):
    """``network.connect`` (not the router's listen address) is what clients verify."""
    cfg = write_config(lab, paper, router="tcp/0.0.0.0:7447", connect="tcp/manager.lab:7447")
    [(_, message)] = problems_of(cfg)
    assert "names DNS:localhost, IP:127.0.0.1 but not manager.lab" in message
    assert "network.connect tcp/manager.lab:7447" in message and "DNS:manager.lab" in message
    _ca(lab).issue(lab / "pki" / "certs", "manager", san=("manager.LAB",))
    assert problems_of(cfg) == []


# --------------------------------------------------------------------------------------------
# login_problem: why a router refuses a client (no zenoh here; real routers in
# tests/integration/test_security_login.py)
# --------------------------------------------------------------------------------------------


@pytest.fixture()
def listener() -> Iterator[int]:
    """A TCP port that accepts connections and never answers."""
    srv = socket.create_server(("127.0.0.1", 0))
    conns: list[socket.socket] = []
    done = threading.Event()

    def serve() -> None:
        srv.settimeout(0.1)
        while not done.is_set():
            try:
                conns.append(srv.accept()[0])
            except TimeoutError:
                continue
            except OSError:
                return

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    yield srv.getsockname()[1]
    done.set()
    t.join(5)
    srv.close()
    for c in conns:
        c.close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_login_problem_names_the_node_and_the_password_file(lab, paper, listener):
    (lab / "creds.txt").write_text("S1:pw\n")
    data = normalised(paper)
    data["network"]["security"] = {"credentials_file": "creds.txt"}
    cfg = lab / "pw.yaml"
    cfg.write_text(yaml.safe_dump(data, sort_keys=False))
    net = load(cfg).network
    assert login_problem(net, "S1", f"tcp/127.0.0.1:{listener}") == (
        f"authentication failed for S1 (the password in {lab / 'creds.txt'} is not the "
        "router's, or the router does not accept user S1)"
    )
    # nobody listens: the router is not up (yet), nothing to tell
    assert login_problem(net, "S1", f"tcp/127.0.0.1:{_free_port()}") is None
    assert login_problem(paper.network, "S1", f"tcp/127.0.0.1:{listener}") is None  # no security


@pytest.fixture(params=["reset", "closed"])
def exiting_router(request) -> Iterator[int]:
    """A TCP port whose owner accepts each connection and drops it at once, as a router process
    that is exiting does (its kernel still accepts): reset (SO_LINGER 0) or closed."""
    srv = socket.create_server(("127.0.0.1", 0))
    done = threading.Event()

    def serve() -> None:
        srv.settimeout(0.1)
        while not done.is_set():
            try:
                conn = srv.accept()[0]
            except TimeoutError:
                continue
            except OSError:
                return
            if request.param == "reset":
                conn.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            conn.close()

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    yield srv.getsockname()[1]
    done.set()
    t.join(5)
    srv.close()


def test_a_router_that_drops_the_connection_is_no_verdict_on_the_node(lab, paper, exiting_router):
    """When another node's failure stops a run, the router exits while the others still try to
    log in: its kernel accepts and drops their probes. That said "authentication failed for
    world (the password ... is not the router's ...)" of nodes whose password was right (and
    the same with TLS on, whose probe ended without an alert); a dropped connection tells
    nothing (None), with passwords and with TLS."""
    (lab / "creds.txt").write_text("S1:pw\n")
    data = normalised(paper)
    data["network"]["security"] = {"credentials_file": "creds.txt"}
    pw = lab / "pw.yaml"
    pw.write_text(yaml.safe_dump(data, sort_keys=False))
    assert login_problem(load(pw).network, "S1", f"tcp/127.0.0.1:{exiting_router}") is None
    tls = load(write_config(lab, paper)).network
    assert login_problem(tls, "S1", f"tls/127.0.0.1:{exiting_router}", timeout_s=1.0) is None


def test_login_problem_tls_to_something_that_does_not_speak_tls(lab, paper, listener):
    net = load(write_config(lab, paper)).network
    problem = login_problem(net, "S1", f"tls/127.0.0.1:{listener}", timeout_s=0.3)
    assert problem is not None and problem.startswith("TLS handshake failed for S1 (")
    assert "did not complete a TLS handshake" in problem


def test_the_router_given_on_the_command_line_is_the_one_checked(lab, paper):
    """``covnet up --router tcp/127.0.0.2:P``: the clients connect there, but the check named
    the config's router: a certificate for 127.0.0.2 was refused and one for 127.0.0.1 only
    passed (every client then failed its TLS handshake)."""
    sc = load(write_config(lab, paper))
    assert certificate_problems(sc.network, ["manager"]) == []  # the config's 127.0.0.1
    [(_, message)] = certificate_problems(sc.network, ["manager"], "tcp/127.0.0.2:7447")
    assert "but not 127.0.0.2" in message and "--router tcp/127.0.0.2:7447" in message
    _ca(lab).issue(lab / "pki" / "certs", "manager", san=("127.0.0.2",))
    assert certificate_problems(sc.network, ["manager"], "tcp/127.0.0.2:7447") == []


def test_check_asks_for_no_recorder_without_a_recording(lab, paper, capsys):
    """``covnet check`` of a config with ``network.record: false`` wanted the recorder's
    certificate (exit 2) while ``covnet up`` ran it: no recorder runs."""
    cfg = write_config(lab, paper)  # record: false, and the lab has no recorder certificate
    for ext in ("pem", "key"):
        (lab / "pki" / "certs" / f"recorder.{ext}").unlink(missing_ok=True)
    rc, err = check(cfg, capsys)
    assert rc == 0, err
    data = yaml.safe_load(cfg.read_text())
    data["network"]["record"] = True
    cfg.write_text(yaml.safe_dump(data, sort_keys=False))
    rc, err = check(cfg, capsys)
    assert rc == 2 and "recorder" in err, err
