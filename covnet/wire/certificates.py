"""The TLS files of a covnet network (``network.security.tls``): every certificate checked as
zenoh (rustls with ring, webpki) will check it, before anything starts
(:func:`certificate_problems`, called by :func:`covnet.wire.security.preflight`), and why a running
client's session does not open (:func:`login_problem`: a TCP connection and a TLS handshake of
its own).  The rest of the network's security (credentials, access control, the zenoh
settings) is :mod:`covnet.wire.security`'s."""

from __future__ import annotations

import ipaddress
import socket
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

from covnet.config import NetworkSpec, TlsSpec
from covnet.wire.messages import MANAGER_ID

if TYPE_CHECKING:  # imported where used: node processes do not need it (start-up time)
    from cryptography import x509

__all__ = ["certificate_problems", "login_problem"]

_SEC = "network.security"


def _pem_problem(path: Path, what: str) -> str | None:
    if not path.is_file():
        return f"{what} {str(path)!r} does not exist or is not a file"
    try:
        head = path.read_bytes()[: 1 << 16]
    except OSError as exc:
        return f"cannot read {what} {str(path)!r}: {exc.strerror or exc}"
    if b"-----BEGIN " not in head:
        return f"{what} {str(path)!r} is not a PEM file"
    return None


# --------------------------------------------------------------------------------------------
# certificates: what zenoh (rustls with ring, webpki) will accept, checked before anything
# starts; and why a running client's session does not open
# --------------------------------------------------------------------------------------------

_CA_FIELD = f"{_SEC}.tls.ca"
_DIR_FIELD = f"{_SEC}.tls.cert_dir"

_KEY_USAGES = (
    ("digital_signature", "digitalSignature"),
    ("content_commitment", "nonRepudiation"),
    ("key_encipherment", "keyEncipherment"),
    ("data_encipherment", "dataEncipherment"),
    ("key_agreement", "keyAgreement"),
    ("key_cert_sign", "keyCertSign"),
    ("crl_sign", "cRLSign"),
)


def _when(t: datetime) -> str:
    return t.strftime("%Y-%m-%d %H:%M:%S UTC")


def _validity(cert: x509.Certificate, now: datetime) -> str | None:
    start, end = cert.not_valid_before_utc, cert.not_valid_after_utc
    if now < start:
        return f"is not valid yet: valid from {_when(start)} to {_when(end)} (now {_when(now)})"
    if now > end:
        return f"expired on {_when(end)} (valid from {_when(start)}; now {_when(now)})"
    return None


def _key_problem(key: object) -> str | None:
    """The public key is one rustls (with ring, as zenoh builds it) can use, or what it is."""
    # cryptography: start-up of the nodes, which never check certificates
    from cryptography.hazmat.primitives.asymmetric import ec, ed25519, rsa

    supported = "zenoh (rustls) takes RSA keys of 2048 to 8192 bits, EC P-256 or P-384, Ed25519"
    if isinstance(key, rsa.RSAPublicKey):
        if 2048 <= key.key_size <= 8192:
            return None
        return f"has a {key.key_size}-bit RSA key; {supported}"
    if isinstance(key, ec.EllipticCurvePublicKey):
        if key.curve.name in ("secp256r1", "secp384r1"):
            return None
        return f"has an EC key on curve {key.curve.name}; {supported}"
    if isinstance(key, ed25519.Ed25519PublicKey):
        return None
    kind = type(key).__name__.lstrip("_").removesuffix("PublicKey") or "unknown"
    return f"has a {kind} key; {supported}"


def _signature_problem(cert: x509.Certificate, issuer_key: object) -> str | None:
    """The signature algorithm is one webpki verifies (ECDSA with SHA-256/384, RSA with
    SHA-256/384/512, Ed25519)."""
    # cryptography: start-up of the nodes, which never check certificates
    from cryptography.hazmat.primitives.asymmetric import ec, rsa

    digest = cert.signature_hash_algorithm
    name = digest.name if digest is not None else None
    if isinstance(issuer_key, ec.EllipticCurvePublicKey):
        ok, alg = name in ("sha256", "sha384"), "ECDSA"
    elif isinstance(issuer_key, rsa.RSAPublicKey):
        ok, alg = name in ("sha256", "sha384", "sha512"), "RSA"
    else:
        return None  # Ed25519 (no digest), or a key _key_problem reports on the issuer
    if ok:
        return None
    return (
        f"is signed with {alg} and {(name or 'no digest').upper()}, which zenoh (rustls) does not "
        "verify; expected SHA-256 or SHA-384 (openssl x509 -req -sha256)"
    )


def _load_certs(path: Path) -> tuple[list[x509.Certificate], str | None]:
    """Every certificate in a PEM file, or why there are none."""
    # cryptography: start-up of the nodes, which never check certificates
    from cryptography import x509

    try:
        certs = x509.load_pem_x509_certificates(path.read_bytes())
    except OSError as exc:
        return [], f"cannot be read: {exc.strerror or exc}"
    except x509.InvalidVersion as exc:
        return [], f"is X.509 v{exc.parsed_version + 1}; expected v3"
    except ValueError:  # cryptography's message is its ASN.1 parser's
        return [], "is not a valid PEM certificate (the PEM body is not an X.509 certificate)"
    return certs, None


def _ca_problems(path: Path, now: datetime) -> tuple[list[x509.Certificate], list[str]]:
    """The CA certificate(s) in ``path`` and what is wrong with them: X.509 v3, basicConstraints
    CA:TRUE, keyUsage (when present) with keyCertSign, valid now, a key rustls can verify
    signatures with."""
    # cryptography: start-up of the nodes, which never check certificates
    from cryptography import x509

    cas, problem = _load_certs(path)
    name = f"the CA certificate {str(path)!r}"
    if problem:
        return [], [f"{name} {problem}"]
    problems: list[str] = []
    for i, ca in enumerate(cas):
        who = name if len(cas) == 1 else f"{name} (certificate {i + 1} of {len(cas)})"
        if ca.version != x509.Version.v3:
            problems.append(
                f"{who} is X.509 {ca.version.name}; expected v3 with basicConstraints "
                "critical,CA:TRUE and keyUsage keyCertSign"
            )
        else:
            try:
                bc = ca.extensions.get_extension_for_class(x509.BasicConstraints).value
            except x509.ExtensionNotFound:
                problems.append(
                    f"{who} has no basicConstraints extension; expected basicConstraints "
                    "critical,CA:TRUE"
                )
            else:
                if not bc.ca:
                    problems.append(
                        f"{who} has basicConstraints CA:FALSE (it is not a CA); expected CA:TRUE"
                    )
            try:
                ku = ca.extensions.get_extension_for_class(x509.KeyUsage).value
            except x509.ExtensionNotFound:
                pass
            else:
                if not ku.key_cert_sign:
                    problems.append(
                        f"{who} has keyUsage {_usages(ku)} without keyCertSign; expected "
                        "keyUsage keyCertSign (and cRLSign)"
                    )
        for problem in (_validity(ca, now), _key_problem(ca.public_key())):
            if problem:
                problems.append(f"{who} {problem}")
    return cas, problems


def _usages(ku: x509.KeyUsage) -> str:
    return ",".join(label for attr, label in _KEY_USAGES if getattr(ku, attr)) or "(none)"


def _eku_names(eku: x509.ExtendedKeyUsage) -> str:
    # cryptography: start-up of the nodes, which never check certificates
    from cryptography.x509.oid import ExtendedKeyUsageOID as E

    known = {
        E.SERVER_AUTH: "serverAuth",
        E.CLIENT_AUTH: "clientAuth",
        E.CODE_SIGNING: "codeSigning",
        E.EMAIL_PROTECTION: "emailProtection",
        E.TIME_STAMPING: "timeStamping",
        E.OCSP_SIGNING: "OCSPSigning",
        E.ANY_EXTENDED_KEY_USAGE: "anyExtendedKeyUsage",
    }
    return ",".join(known.get(oid, oid.dotted_string) for oid in eku) or "(none)"


def _issuer_problem(
    cert: x509.Certificate,
    intermediates: Sequence[x509.Certificate],
    cas: Sequence[x509.Certificate],
    ca_path: str,
) -> str | None:
    """``cert`` is signed by one of ``cas``, directly or through the ``intermediates`` that
    follow it in its file (names and signatures checked, and the signature algorithm)."""
    # cryptography: start-up of the nodes, which never check certificates
    from cryptography.exceptions import InvalidSignature, UnsupportedAlgorithm

    pool = list(intermediates)
    cur = cert
    while True:
        ca = next((c for c in cas if c.subject == cur.issuer), None)
        issuer = ca or next((c for c in pool if c.subject == cur.issuer), None)
        if issuer is None:
            subjects = " or ".join(repr(c.subject.rfc4514_string()) for c in cas)
            return (
                f"is not signed by the CA {ca_path!r}: its issuer is "
                f"{cur.issuer.rfc4514_string()!r}, the CA is {subjects}"
            )
        try:
            cur.verify_directly_issued_by(issuer)
        except InvalidSignature:
            signer = f"the CA {ca_path!r}" if ca is not None else "the intermediate CA"
            return (
                f"names {issuer.subject.rfc4514_string()!r} as its issuer, but the key of "
                f"{signer} of that name did not sign it (another CA of the same name?); "
                f"expected a certificate signed by the CA {ca_path!r}"
            )
        except (ValueError, TypeError, UnsupportedAlgorithm) as exc:
            return (
                f"cannot be checked against its issuer {issuer.subject.rfc4514_string()!r}: {exc}"
            )
        problem = _signature_problem(cur, issuer.public_key())
        if problem:
            return problem
        if ca is not None:
            return None
        pool.remove(issuer)
        cur = issuer


def _dns_matches(pattern: str, host: str) -> bool:
    """webpki's rule: case-insensitive; ``*.`` stands for exactly one leftmost label."""
    pattern, host = pattern.lower().rstrip("."), host.lower().rstrip(".")
    if pattern.startswith("*."):
        first, _, rest = host.partition(".")
        return bool(first) and rest == pattern[2:]
    return pattern == host


def _san_problem(cert: x509.Certificate, host: str, field: str) -> str | None:
    """The router's certificate names ``host`` (the one clients connect to) in its
    subjectAltName: what rustls checks with ``verify_name`` (it never looks at the CN)."""
    # cryptography: start-up of the nodes, which never check certificates
    from cryptography import x509

    try:
        san: x509.SubjectAlternativeName | None = cert.extensions.get_extension_for_class(
            x509.SubjectAlternativeName
        ).value
    except x509.ExtensionNotFound:
        san = None
    dns = san.get_values_for_type(x509.DNSName) if san else []
    ips = san.get_values_for_type(x509.IPAddress) if san else []
    try:
        ip: ipaddress.IPv4Address | ipaddress.IPv6Address | None = ipaddress.ip_address(host)
    except ValueError:
        ip = None
    if (ip in ips) if ip is not None else any(_dns_matches(n, host) for n in dns):
        return None
    names = [f"DNS:{n}" for n in dns] + [f"IP:{a}" for a in ips]
    want = f"IP:{host}" if ip is not None else f"DNS:{host}"
    has = f"names {', '.join(names)} but not {host}" if names else "has no subjectAltName"
    return (
        f"{has}: the clients connect to {host} ({field}) and with verify_name: true accept "
        f"the router only if its certificate's subjectAltName has {want} (add it, or set "
        f"{_SEC}.tls.verify_name: false)"
    )


def _endpoint_host_port(ep: str) -> tuple[str, int] | None:
    """``(host, port)`` of ``proto/host:port`` (zenoh's ``?``/``#`` suffixes dropped)."""
    rest = ep.partition("/")[2].split("?")[0].split("#")[0]
    host, _, port = rest.rpartition(":")
    if not host or not port.isdigit():
        return None
    return host.strip("[]"), int(port)


def _node_problems(
    tls: TlsSpec,
    name: str,
    cas: Sequence[x509.Certificate],
    connect: tuple[str, str] | None,
    now: datetime,
) -> list[str]:
    """What is wrong with ``name``'s certificate and key in ``tls.cert_dir``."""
    # cryptography: start-up of the nodes, which never check certificates
    from cryptography import x509
    from cryptography.exceptions import UnsupportedAlgorithm
    from cryptography.hazmat.primitives import serialization
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    d = Path(tls.cert_dir)
    cert_path, key_path = d / f"{name}.pem", d / f"{name}.key"
    who = f"{name}'s certificate {str(cert_path)!r}"
    out: list[str] = []
    key = None
    problem = _pem_problem(key_path, f"{name}'s private key")
    if problem:
        out.append(problem)
    else:
        try:
            key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
        except TypeError:  # "Password was not given but private key is encrypted"
            out.append(
                f"{name}'s private key {str(key_path)!r} is encrypted; zenoh needs it "
                "unencrypted (openssl pkey -in KEY -out KEY)"
            )
        except (OSError, ValueError, UnsupportedAlgorithm):
            out.append(
                f"{name}'s private key {str(key_path)!r} is not a PEM private key zenoh can "
                "read (PKCS#8, PKCS#1 RSA or SEC1 EC; RSA, EC P-256/P-384 or Ed25519)"
            )
    problem = _pem_problem(cert_path, f"{name}'s certificate")
    chain, loaded = ([], problem) if problem else _load_certs(cert_path)
    if not chain:
        return [problem if problem else f"{who} {loaded}", *out]
    cert = chain[0]

    def bad(text: str | None) -> None:
        if text:
            out.append(f"{who} {text}")

    if cert.version != x509.Version.v3:
        bad(
            f"is X.509 {cert.version.name}; zenoh (rustls) accepts only v3 and fails with "
            "UnsupportedCertVersion: sign it with an extensions file (openssl x509 -req ... "
            "-extfile node.ext; see the README)"
        )
    bad(_validity(cert, now))
    cns = [str(a.value) for a in cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)]
    if cns != [name]:
        has = (
            f"has common name {cns[0]!r}"
            if len(cns) == 1
            else (f"has common names {cns}" if cns else "has no common name")
        )
        bad(f"{has}; expected {name!r} (the router knows a node by its certificate's common name)")
    if cas:
        bad(_issuer_problem(cert, chain[1:], cas, tls.ca))
    bad(_key_problem(cert.public_key()))
    router = name == MANAGER_ID
    if cert.version == x509.Version.v3:
        ext = cert.extensions
        try:
            if ext.get_extension_for_class(x509.BasicConstraints).value.ca:
                bad(
                    "has basicConstraints CA:TRUE (a CA certificate, which rustls refuses as a "
                    "node's: CaUsedAsEndEntity); expected CA:FALSE"
                )
        except x509.ExtensionNotFound:
            pass
        try:
            ku = ext.get_extension_for_class(x509.KeyUsage).value
            if not ku.digital_signature:
                bad(
                    f"has keyUsage {_usages(ku)} without digitalSignature (the TLS handshake "
                    "signs with this key); expected keyUsage digitalSignature"
                )
        except x509.ExtensionNotFound:
            pass
        purpose, label = (
            (ExtendedKeyUsageOID.SERVER_AUTH, "serverAuth")
            if router
            else (ExtendedKeyUsageOID.CLIENT_AUTH, "clientAuth")
        )
        try:
            eku = ext.get_extension_for_class(x509.ExtendedKeyUsage).value
            if purpose not in eku:
                role = "the router's (the manager's)" if router else "a client's"
                bad(
                    f"has extendedKeyUsage {_eku_names(eku)} without {label}, which {role} "
                    f"certificate needs (the handshake fails); expected extendedKeyUsage {label}"
                )
        except x509.ExtensionNotFound:
            pass
    if router and connect is not None:
        bad(_san_problem(cert, *connect))
    if key is not None:
        der, spki = serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
        if key.public_key().public_bytes(der, spki) != cert.public_key().public_bytes(der, spki):
            out.append(
                f"{name}'s private key {str(key_path)!r} does not match {who} (the "
                "certificate's public key is another key's); expected the key the certificate "
                "was made for"
            )
    return out


def certificate_problems(
    net: NetworkSpec, names: Sequence[str], router: str | None = None
) -> list[tuple[str, str]]:
    """``(path, message)`` for everything zenoh would refuse, or that would make a node
    unknown to the router, in the TLS files of ``names`` (``manager``, ``world``,
    ``recorder``, sensor ids) on this host; empty without TLS.

    The CA certificate (``tls.ca``): X.509 v3, basicConstraints CA:TRUE, keyUsage (if present)
    with keyCertSign, valid now, a supported key. Each node's ``<node>.pem`` and ``<node>.key``:
    both parse, the key is the certificate's (and unencrypted), X.509 v3 (rustls refuses v1:
    UnsupportedCertVersion), valid now, common name = the node id, signed by the CA (names and
    signature; intermediates may follow the certificate in its file) with an algorithm rustls
    verifies, a key type rustls supports, not a CA (basicConstraints CA:TRUE is refused),
    keyUsage (if present) with digitalSignature, extendedKeyUsage (if present) with serverAuth
    for the manager, clientAuth for the others; with ``verify_name``, the manager's
    subjectAltName names the host the clients connect to (``network.connect``, else
    ``network.router``): IP:addr for an address, DNS:name for a name. A missing file is
    reported as such (``file_problems`` reports a missing CA file or certificate directory).
    """
    tls = net.security.tls
    if tls is None:
        return []
    now = datetime.now(UTC)
    problems: list[tuple[str, str]] = []
    cas: list[x509.Certificate] = []
    if _pem_problem(Path(tls.ca), "CA certificate") is None:  # else file_problems says so
        cas, ca_problems = _ca_problems(Path(tls.ca), now)
        problems += [(_CA_FIELD, m) for m in ca_problems]
    if not Path(tls.cert_dir).is_dir():  # file_problems says so
        return problems
    # the endpoint the clients connect to: the config's, or the command line's --router
    # (the check named the config's while the run used --router: a right certificate refused)
    connect: tuple[str, str] | None = None
    where = net.connect or router or net.router
    field = "network.connect" if net.connect else "--router" if router else "network.router"
    hp = _endpoint_host_port(where)
    if tls.verify_name and hp is not None:
        connect = (hp[0], f"{field} {where}")
    for name in names:
        problems += [(_DIR_FIELD, m) for m in _node_problems(tls, name, cas, connect, now)]
    return problems


_ALERTS = {
    "CERTIFICATE_UNKNOWN": "certificate unknown: not X.509 v3, or a CA certificate, ...",
    "BAD_CERTIFICATE": "bad certificate",
    "UNSUPPORTED_CERTIFICATE": "unsupported certificate: extendedKeyUsage without clientAuth?",
    "CERTIFICATE_EXPIRED": "certificate expired, or not valid yet",
    "UNKNOWN_CA": "unknown CA: not signed by the router's CA",
    "DECRYPT_ERROR": "decrypt error: its signature does not verify with the router's CA",
    "CERTIFICATE_REQUIRED": "certificate required",
    "ACCESS_DENIED": "access denied",
}


class _NoVerdict(Exception):
    """The probe's connection went (reset, closed) before it could tell anything: a router
    exiting, not a refusal of this node."""


def _waits_for_us(sock: socket.socket, timeout_s: float) -> bool:
    """Whether the peer keeps the connection open, waiting for us to speak first (a zenoh
    router waits for the client's handshake); raises :class:`_NoVerdict` when it closes or
    resets it (a router exiting: its kernel accepted the connection, nobody will answer)."""
    sock.settimeout(timeout_s)
    try:
        data = sock.recv(1)
    except TimeoutError:
        return True
    except OSError:
        raise _NoVerdict from None
    if not data:
        raise _NoVerdict
    return True  # it spoke first: not a closing listener at least


def _tls_problem(
    tls: TlsSpec, node_id: str, sock: socket.socket, host: str, timeout_s: float
) -> str | None:
    """A TLS handshake over ``sock`` as ``node_id`` (its certificate and the CA, like zenoh's
    client): why it fails, or ``None`` when the router accepted it. In TLS 1.3 the router
    checks the client's certificate after the client's side of the handshake is done, so a
    rejection shows as an alert on the first read. Raises :class:`_NoVerdict` when the
    connection went before the handshake told anything."""
    # start-up: ssl only to diagnose a refused TLS login
    import ssl

    cert = Path(tls.cert_dir) / f"{node_id}.pem"
    key = Path(tls.cert_dir) / f"{node_id}.key"
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.check_hostname = tls.verify_name
    try:
        ctx.load_verify_locations(cafile=tls.ca)
        ctx.load_cert_chain(cert, key, password=lambda: b"")  # never a password prompt
    except (OSError, ssl.SSLError) as exc:
        return f"its certificate {str(cert)!r} or key cannot be used: {exc}; run covnet check"
    # over memory buffers, not ssl's socket wrapper: that one, given a socket the router has
    # just reset, raises from its constructor and leaves its own socket unclosed
    incoming, outgoing = ssl.MemoryBIO(), ssl.MemoryBIO()
    tls_obj = ctx.wrap_bio(incoming, outgoing, server_hostname=host)

    def drive(step: Callable[[], object]) -> None:
        """Run ``step`` of the handshake, sending what it wrote and feeding it what the router
        sends until it needs nothing more; a connection closed meanwhile is no verdict."""
        while True:
            try:
                step()
                return
            except ssl.SSLWantReadError:
                if pending := outgoing.read():
                    sock.sendall(pending)
                data = sock.recv(16384)
                if not data:
                    raise _NoVerdict from None  # closed without an alert: a refusal sends one
                incoming.write(data)

    try:
        sock.settimeout(timeout_s)
        try:
            drive(tls_obj.do_handshake)
        except TimeoutError:
            return (
                f"the router at {host} did not complete a TLS handshake: is it listening on tls/?"
            )
        try:
            drive(lambda: tls_obj.read(1))  # a refusal: an alert here (ssl.SSLError below)
        except TimeoutError:
            return None  # the router waits for zenoh's handshake: TLS went through
        return None
    except ssl.SSLCertVerificationError as exc:
        return f"{node_id} does not accept the router's certificate: {exc.verify_message}"
    except (ssl.SSLEOFError, ssl.SSLZeroReturnError):
        raise _NoVerdict from None  # closed without an alert: a refusal would send one
    except ssl.SSLError as exc:
        reason = str(exc.reason or exc)
        alert = reason.partition("ALERT_")[2]
        if alert:
            what = _ALERTS.get(alert, alert.replace("_", " ").lower())
            return (
                f"the router rejected {node_id}'s certificate {str(cert)!r}: {what}; "
                "covnet check says what is wrong with it"
            )
        return f"the TLS handshake with the router at {host} failed: {reason.lower()}"
    except OSError:
        raise _NoVerdict from None  # the connection went: nothing to tell


PASSWORD_PROBE_S = 0.3
"""How long :func:`login_problem` waits, without TLS, to see that the router keeps the
connection open (a router exiting resets it at once)."""


def login_problem(net: NetworkSpec, node_id: str, ep: str, timeout_s: float = 1.0) -> str | None:
    """Why the router at ``ep`` refuses ``node_id``'s session, when it can be told from here:
    ``"TLS handshake failed for <node> (...)"`` (a TLS handshake as the node, over the
    network, shows which side refuses which certificate) or ``"authentication failed for
    <node> (...)"`` (the router is there, TLS, if on, goes through, and a password is in use);
    ``None`` when security is off, when nothing accepts connections at ``ep`` (the router is
    not up, yet), when the connection is reset or closed before anything is told (a router
    exiting) or when nothing can be told. Opens no zenoh session; takes up to about
    ``2 * timeout_s``."""
    sec = net.security
    hp = _endpoint_host_port(ep)
    if not sec.authenticated or hp is None:
        return None
    host, port = hp
    try:
        sock = socket.create_connection((host, port), timeout=timeout_s)
    except OSError:
        return None
    with sock:
        try:
            if sec.tls is not None:
                problem = _tls_problem(sec.tls, node_id, sock, host, timeout_s)
                if problem:
                    return f"TLS handshake failed for {node_id} ({problem})"
            elif sec.credentials_file is not None:
                _waits_for_us(sock, min(timeout_s, PASSWORD_PROBE_S))
        except _NoVerdict:
            # a router exiting (another node's failure stops the run) accepts and resets: no
            # word on this node's password or certificate
            return None
    if sec.credentials_file is None:
        return None
    return (
        f"authentication failed for {node_id} (the password in {sec.credentials_file} is not "
        f"the router's, or the router does not accept user {node_id})"
    )
