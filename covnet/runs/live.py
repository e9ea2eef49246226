"""``covnet up --foxglove HOST:PORT``: the visual channels (:mod:`covnet.runs.visual`) served live
over
the Foxglove WebSocket protocol, by the Foxglove SDK's server, from the recorder process.

The recorder builds each scan's visual messages once (they also go into ``recording.mcap``);
:class:`LiveView` logs the same bytes, with the same schemas, on one SDK channel per topic of
its own :class:`foxglove.Context` (nothing else of the process is served).  Logging to a
channel nobody subscribed to costs next to nothing; a slow client loses the oldest messages
(the SDK's per-client backlog), never the run.
"""

from __future__ import annotations

import socket

import foxglove

from covnet.runs.visual import ENCODINGS, SCHEMAS, TOPICS, VisualMessage

__all__ = ["DEFAULT_ADDRESS", "LiveView", "address_problem", "parse_address"]

DEFAULT_ADDRESS = "127.0.0.1:8765"


def parse_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` -> ``(host, port)``; ValueError with a readable reason."""
    host, sep, port = text.rpartition(":")
    host = host.strip("[]")
    if not sep or not host:
        raise ValueError(f"expected HOST:PORT (e.g. {DEFAULT_ADDRESS}), got {text!r}")
    if not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ValueError(f"port must be a number in 1..65535, got {port!r}")
    return host, int(port)


def address_problem(text: str) -> str | None:
    """Why ``text`` cannot be served on (not ``HOST:PORT``, the host is not an address of this
    machine, the port is taken), or None: checked before ``covnet up`` starts anything."""
    try:
        host, port = parse_address(text)
    except ValueError as exc:
        return str(exc)
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except OSError as exc:
        return f"cannot resolve {host!r}: {exc.strerror or exc}"
    family, _, _, _, sockaddr = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(sockaddr)
        except OSError as exc:
            return f"cannot listen on {host}:{port}: {exc.strerror or exc}"
    return None


class LiveView:
    """A Foxglove WebSocket server on ``host:port`` with the visual topics advertised."""

    def __init__(self, host: str, port: int, *, name: str = "covnet") -> None:
        self.context = foxglove.Context()
        self.channels = {
            topic: foxglove.Channel(
                topic,
                schema=SCHEMAS[topic],
                message_encoding=ENCODINGS[topic],
                context=self.context,
            )
            for topic in TOPICS
        }
        self.server = foxglove.start_server(name=name, host=host, port=port, context=self.context)
        self.sent = 0

    @property
    def port(self) -> int:
        return int(self.server.port)

    def send(self, vm: VisualMessage) -> None:
        self.channels[vm.topic].log(vm.data, log_time=vm.log_time_ns)
        self.sent += 1

    def close(self) -> None:
        for ch in self.channels.values():
            ch.close()
        self.server.stop()
