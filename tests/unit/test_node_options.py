"""The node processes started by hand (``python -m sensors|world|recorder|manager``, README
*Several hosts*) check the options that name the wire before a session opens, as ``covnet up``
does: a malformed ``--connect`` / ``--listen`` was retried until ``ready_timeout_s``, and a run
id with a ``/`` went on to connect; both are usage errors (exit 2) now."""

from __future__ import annotations

import importlib
import signal

import pytest


@pytest.fixture(autouse=True)
def _own_signal_handlers():
    """A node's main installs its SIGINT/SIGTERM handlers: the test's process gets its own
    back (later tests in this worker rely on Ctrl-C raising KeyboardInterrupt)."""
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    yield
    for s, handler in saved.items():
        signal.signal(s, handler)


BAD = [
    (["--run", "a/b"], "--run: invalid run id 'a/b'"),
    (["--run", "*"], "--run: invalid run id '*'"),
]


@pytest.mark.parametrize(
    ("prog", "argv", "message"),
    [
        ("sensors", ["--id", "S1", "--connect", "garbage"], "--connect: expected a zenoh endpoint"),
        ("sensors", ["--id", "S1", "--connect", "tcp/127.0.0.1"], "--connect: expected a zenoh"),
        ("world", ["--connect", "garbage"], "--connect: expected a zenoh endpoint"),
        ("recorder", ["--connect", "garbage", "--out", "{tmp}/r.mcap"], "--connect: expected"),
        ("manager", ["--listen", "garbage", "--out", "{tmp}/m"], "--listen: expected a zenoh"),
        *[("sensors", ["--id", "S1", *a], m) for a, m in BAD],
        *[("manager", ["--out", "{tmp}/m", *a], m) for a, m in BAD],
    ],
)
def test_a_node_names_a_bad_endpoint_or_run_id_before_connecting(
    prog, argv, message, paper_path, tmp_path, capsys
):
    main = importlib.import_module(f"{prog}.__main__").main
    args = ["--config", str(paper_path), *[a.format(tmp=tmp_path) for a in argv]]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert f"{prog}: error: {message}" in err and "Traceback" not in err
