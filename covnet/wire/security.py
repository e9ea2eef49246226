"""Zenoh access control, user/password authentication and mutual TLS for a covnet network.

Everything here is off unless ``network.security`` in the config turns it on; then
:func:`zenoh_settings` gives each process the extra zenoh settings (``path -> value``, for
``zenoh_config(..., extra_json5=...)``) and :func:`endpoint` turns ``tcp/`` endpoints into
``tls/`` ones when TLS is on. This module builds no zenoh object and imports no zenoh.

Topology and identities
-----------------------
The manager's session is the router; world, recorder and sensors are clients of it. A node's
identity is its node id: ``world``, ``recorder``, or its sensor id. With ``credentials_file`` a
client authenticates as ``user = node id`` with the password from that file (zenoh ``usrpwd``:
a challenge/response HMAC, the password itself is not sent), and the router checks every client
against the whole file (``transport/auth/usrpwd/dictionary_file``); a wrong or unknown user, or
none, makes the client's ``zenoh.open`` fail at once. With ``tls`` every link is mutual TLS 1.3:
the router presents ``cert_dir/manager.pem``, each client ``cert_dir/<node id>.pem``; both sides
require a certificate signed by ``tls.ca``, so a client without one cannot open a session. The
certificate's common name is the node's identity for access control.

``covnet check`` and ``covnet up`` call :func:`preflight` before anything starts: the files and
passwords, and every certificate as zenoh (rustls) will use it
(:func:`covnet.wire.certificates.certificate_problems`: X.509 v3, dates, common name, CA chain,
extensions, the router's subjectAltName). A client whose session does not open asks
:func:`covnet.wire.certificates.login_problem` why (a TCP connection and a TLS handshake of its
own): ``authentication failed for <node> (...)`` or ``TLS handshake failed for <node>
(...)``, rather than zenoh's bare "Unable to connect".

What access control enforces (``access_control: true``; on the router only)
-------------------------------------------------------------------------------
Zenoh's ACL (``access_control`` in its config) filters the messages the router receives from
(*ingress*) and sends to (*egress*) each client's transport, by the client's identity (a
*subject*: ``usernames: [id]`` with a credentials file, ``cert_common_names: [id]`` with TLS,
both when both are on, and then both must match). ``default_permission`` is ``deny``: whatever no
rule allows is dropped, silently. ``<run>`` below is the wildcard ``*``: the rules do not depend
on the run id. Every known identity (``world``, ``recorder``, each sensor id) gets:

======================  ========  ===========================================================
rule                    flow      allows
======================  ========  ===========================================================
``covnet-read``         egress    ``put``, ``declare_subscriber``, ``liveliness_token``,
                                  ``declare_liveliness_subscriber``, ``liveliness_query`` on
                                  ``covnet/*/**``: every node may read every covnet key
``covnet-subscribe``    ingress   ``declare_subscriber``, ``declare_liveliness_subscriber``,
                                  ``liveliness_query`` on ``covnet/*/**``
``publish-<id>``        ingress   ``put`` on the node's own keys only:
                                  sensor S: ``covnet/*/sensor/S/meas``, ``covnet/*/hb/sensor/S``;
                                  world: ``covnet/*/truth``, ``covnet/*/hb/world/world``;
                                  recorder: ``covnet/*/hb/recorder/recorder``
``token-<id>``          ingress   ``liveliness_token`` on ``covnet/*/alive/<role>/<id>`` only
======================  ========  ===========================================================

So, from any remote session: a ``put`` on the command key ``covnet/*/cmd`` (and on ``track``,
``manager/status``, the manager's heartbeat and liveliness keys, another node's keys, or
anything outside ``covnet/<run>/``) is dropped by the router; so are every ``delete``, ``query``,
``reply`` and ``declare_queryable``; an identity the rules do not name (a valid password or
certificate for a user not in the list above) can neither publish nor receive anything. The
manager publishes commands from inside the router: zenoh applies the ACL to transports only,
not to the router's own session, so its commands always go out. Not enforced: who may *read*
(every covnet identity reads every covnet key: truth, commands and measurements are not
secrets between the nodes of one run); the payload's claimed sensor id (the manager already
checks it against the key); anything on a host that runs several nodes under one user account
(the key files and the credentials file are readable by all of them).

Threat model
------------
A lab network: keep stray and misconfigured processes (another run, a test, a student's
script) from commanding sensors or forging measurements, and keep hosts that do not hold a
password or a CA-signed certificate out of the network. The credentials file is plain text,
shared by the nodes of a run: not a secret store (anyone who reads it can impersonate every
node). Over plain TCP, user/password neither encrypts the traffic nor proves the router's
identity to the clients, and a captured challenge/response allows offline guessing of a weak
password. Mutual TLS is the stronger option (each host holds only its own key) and the only one
that also authenticates the router and encrypts the traffic; use both (TLS for the channel,
passwords as a second factor) on a shared network. Test certificates are generated by the
tests; never commit private keys.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from covnet.config import ConfigError, Networked, NetworkSpec
from covnet.wire import messages as msg
from covnet.wire.certificates import (
    _DIR_FIELD,
    _SEC,
    _pem_problem,
    certificate_problems,
    login_problem,
)
from covnet.wire.messages import MANAGER_ID, RECORDER_ID, RESERVED_IDS, WORLD_ID

__all__ = [
    "MANAGER_ID",
    "RECORDER_ID",
    "RESERVED_IDS",
    "WORLD_ID",
    "access_control",
    "certificate_problems",
    "endpoint",
    "file_problems",
    "login_problem",
    "preflight",
    "read_credentials",
    "zenoh_settings",
]

_ROLES = ("manager", "world", "sensor", "recorder")
_RUN = "RUN0"  # a placeholder run id, replaced by the wildcard '*' in ACL key expressions


# --------------------------------------------------------------------------------------------
# endpoints
# --------------------------------------------------------------------------------------------


def endpoint(net: NetworkSpec, ep: str) -> str:
    """``ep`` as this network uses it: with ``security.tls`` a ``tcp/`` endpoint becomes
    ``tls/`` (same host and port); otherwise unchanged."""
    proto, _, rest = ep.partition("/")
    if net.security.tls is not None and proto == "tcp":
        return f"tls/{rest}"
    return ep


# --------------------------------------------------------------------------------------------
# validation: the shape when a config is loaded, the files when a process needs them
# --------------------------------------------------------------------------------------------


def read_credentials(path: str | Path) -> dict[str, str]:
    """``user -> password`` from a credentials file, parsed as zenoh parses its
    ``dictionary_file``: one ``user:password`` per line (split at the first ``:``, both sides
    stripped, both non-empty), blank lines ignored. ``ValueError`` names the line (never the
    password); ``OSError`` if it cannot be read."""
    out: dict[str, str] = {}
    text = Path(path).read_text(encoding="utf-8")
    for n, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line:
            continue
        user, sep, password = line.partition(":")
        user, password = user.strip(), password.strip()
        if not sep:
            raise ValueError(f"line {n}: expected 'user:password'")
        if not user:
            raise ValueError(f"line {n}: empty user")
        if not password:
            raise ValueError(f"line {n}: empty password for user {user!r}")
        if user in out:
            raise ValueError(f"line {n}: user {user!r} appears twice")
        out[user] = password
    return out


def file_problems(net: NetworkSpec) -> list[tuple[str, str]]:
    """``(path, message)`` for each file named by ``network.security`` that is missing or
    unreadable: the credentials file (parsed), the CA certificate, the certificate directory."""
    sec = net.security
    problems: list[tuple[str, str]] = []
    if sec.credentials_file is not None:
        path = Path(sec.credentials_file)
        if not path.is_file():
            problems.append(
                (f"{_SEC}.credentials_file", f"{str(path)!r} does not exist or is not a file")
            )
        else:
            try:
                read_credentials(path)
            except OSError as exc:
                problems.append(
                    (f"{_SEC}.credentials_file", f"cannot read {str(path)!r}: {exc.strerror}")
                )
            except (ValueError, UnicodeDecodeError) as exc:
                problems.append((f"{_SEC}.credentials_file", f"{str(path)!r}: {exc}"))
    if sec.tls is not None:
        problem = _pem_problem(Path(sec.tls.ca), "CA certificate")
        if problem:
            problems.append((f"{_SEC}.tls.ca", problem))
        if not Path(sec.tls.cert_dir).is_dir():
            problems.append(
                (
                    f"{_SEC}.tls.cert_dir",
                    f"{sec.tls.cert_dir!r} does not exist or is not a directory",
                )
            )
    return problems


def preflight(
    sc: Networked, names: Sequence[str], source: str = "config", router: str | None = None
) -> None:
    """Check, before any process starts, that every one of ``names`` (process names as
    ``covnet up`` uses them: ``manager``, ``world``, ``recorder``, sensor ids) will find its
    files, password and certificate on this host, and that the certificates are ones zenoh will
    accept (:func:`certificate_problems`; ``router``: ``covnet up --router``, the endpoint the
    clients connect to when the config names none); one :class:`ConfigError` lists them all."""
    net = sc.network
    problems = file_problems(net)
    if not problems:
        for name in names:
            role = name if name in RESERVED_IDS else "sensor"
            try:
                zenoh_settings(net, role, name, listen=role == "manager", sensor_ids=sc.sensor_ids)
            except ConfigError as exc:
                # not the key and certificate files: certificate_problems names them per node
                problems += [p for p in exc.problems if p not in problems and p[0] != _DIR_FIELD]
    problems += [p for p in certificate_problems(net, names, router) if p not in problems]
    if problems:
        raise ConfigError(source, problems)


# --------------------------------------------------------------------------------------------
# access control
# --------------------------------------------------------------------------------------------


def _any_run(key: str) -> str:
    """A key built with the placeholder run id, as an expression matching every run."""
    chunks = key.split("/")
    assert chunks.count(_RUN) == 1, key
    return "/".join("*" if c == _RUN else c for c in chunks)


def _own_keys(role: str, node_id: str) -> tuple[list[str], list[str]]:
    """``(put keys, liveliness keys)`` a node may publish, for any run."""
    puts = [msg.heartbeat_key(_RUN, role, node_id)]
    if role == "sensor":  # its measurements or local tracks; in peer mode its own track/status
        puts[:0] = [
            msg.measurement_key(_RUN, node_id),
            msg.peer_track_key(_RUN, node_id),
            msg.peer_status_key(_RUN, node_id),
        ]
    elif role == "world":
        puts.insert(0, msg.truth_key(_RUN))
    tokens = [msg.alive_key(_RUN, role, node_id)]
    return [_any_run(k) for k in puts], [_any_run(k) for k in tokens]


def _root_expr() -> str:
    return _any_run(msg.run_keyexpr(_RUN))  # covnet/*/**: every key of every run


def access_control(net: NetworkSpec, sensor_ids: Sequence[str]) -> dict[str, object]:
    """The router's zenoh ``access_control`` object (see the module docstring)."""
    sec = net.security
    if not sec.authenticated:
        raise ValueError("access control needs credentials_file and/or tls")
    if not sensor_ids:
        raise ValueError("access control needs the config's sensor ids")
    root = _root_expr()
    nodes = [("world", WORLD_ID), ("recorder", RECORDER_ID)]
    nodes += [("sensor", sid) for sid in sensor_ids]
    rules: list[dict[str, object]] = [
        {
            "id": "covnet-read",
            "messages": [
                "put",
                "declare_subscriber",
                "liveliness_token",
                "declare_liveliness_subscriber",
                "liveliness_query",
            ],
            "flows": ["egress"],
            "permission": "allow",
            "key_exprs": [root],
        },
        {
            "id": "covnet-subscribe",
            "messages": ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
            "flows": ["ingress"],
            "permission": "allow",
            "key_exprs": [root],
        },
    ]
    subjects: list[dict[str, object]] = []
    policies: list[dict[str, object]] = []
    for role, nid in nodes:
        puts, tokens = _own_keys(role, nid)
        rules.append(
            {
                "id": f"publish-{nid}",
                "messages": ["put"],
                "flows": ["ingress"],
                "permission": "allow",
                "key_exprs": puts,
            }
        )
        rules.append(
            {
                "id": f"token-{nid}",
                "messages": ["liveliness_token"],
                "flows": ["ingress"],
                "permission": "allow",
                "key_exprs": tokens,
            }
        )
        subject: dict[str, object] = {"id": f"node-{nid}"}
        if sec.credentials_file is not None:
            subject["usernames"] = [nid]
        if sec.tls is not None:
            subject["cert_common_names"] = [nid]
        subjects.append(subject)
        policies.append(
            {
                "id": f"policy-{nid}",
                "rules": ["covnet-read", "covnet-subscribe", f"publish-{nid}", f"token-{nid}"],
                "subjects": [f"node-{nid}"],
            }
        )
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


# --------------------------------------------------------------------------------------------
# per-process settings
# --------------------------------------------------------------------------------------------


def _check_identity(role: str, node_id: str) -> None:
    if role not in _ROLES:
        raise ValueError(f"role must be one of {_ROLES}, got {role!r}")
    if role != "sensor" and node_id != role:
        raise ValueError(f"the {role}'s node id is {role!r}, got {node_id!r}")
    if role == "sensor" and node_id in RESERVED_IDS:
        raise ValueError(f"a sensor cannot use the reserved node id {node_id!r}")


def zenoh_settings(
    net: NetworkSpec,
    role: str,
    node_id: str,
    *,
    listen: bool,
    sensor_ids: Sequence[str] = (),
    source: str = "config",
) -> dict[str, object]:
    """The extra zenoh settings (``path -> value``) of one process under ``net.security``;
    ``{}`` when security is off.

    - ``role``/``node_id``: ``("manager", "manager")``, ``("world", "world")``,
      ``("recorder", "recorder")`` or ``("sensor", <sensor id>)``.
    - ``listen``: this process is the router (the manager): it gets the access control rules
      (then ``sensor_ids``, the config's, are required), the credentials dictionary and the
      TLS server side with client certificates required. Otherwise it is a client: it gets its
      user/password and its client certificate.
    - ``source``: names the config in errors.

    Raises :class:`~covnet.config.ConfigError` when a file this process needs is missing
    (its certificate, its password), ``ValueError`` on a wrong ``role``/``node_id``.
    """
    _check_identity(role, node_id)
    sec = net.security
    problems = file_problems(net)
    if problems:
        raise ConfigError(source, problems)
    out: dict[str, object] = {}
    if sec.credentials_file is not None:
        field = f"{_SEC}.credentials_file"
        creds = read_credentials(sec.credentials_file)
        if listen:
            needed = [WORLD_ID, *sensor_ids] + ([RECORDER_ID] if net.record else [])
            missing = [n for n in needed if n not in creds]
            if missing:
                problems.append((field, f"no password for the node(s) {missing}"))
            out["transport/auth/usrpwd/dictionary_file"] = sec.credentials_file
        elif node_id not in creds:
            problems.append((field, f"no password for this node ({node_id!r})"))
        else:
            out["transport/auth/usrpwd/user"] = node_id
            out["transport/auth/usrpwd/password"] = creds[node_id]
    if sec.tls is not None:
        tls = sec.tls
        cert = Path(tls.cert_dir) / f"{node_id}.pem"
        key = Path(tls.cert_dir) / f"{node_id}.key"
        for path, what in ((cert, "certificate"), (key, "private key")):
            problem = _pem_problem(path, f"this node's {what}")
            if problem:
                problems.append((f"{_SEC}.tls.cert_dir", problem))
        side = "listen" if listen else "connect"
        out["transport/link/tls/root_ca_certificate"] = tls.ca
        out[f"transport/link/tls/{side}_certificate"] = str(cert)
        out[f"transport/link/tls/{side}_private_key"] = str(key)
        out["transport/link/tls/enable_mtls"] = True
        if not listen:
            out["transport/link/tls/verify_name_on_connect"] = tls.verify_name
    if problems:
        raise ConfigError(source, problems)
    if listen and sec.access_control:
        out["access_control"] = access_control(net, sensor_ids)
    return out
