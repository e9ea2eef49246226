"""Real emulated network paths between network namespaces (see ``docs/netem.md``).

:func:`emulated_link` builds one link with the delay, jitter and loss of two
:class:`covnet.core.delay.LinkSpec` s, by ``tc netem`` where the kernel has it and by a userspace
TUN forwarder otherwise; :func:`namespaces` makes throwaway namespaces to put it between.
"""

from __future__ import annotations

from covnet.processes.netem.detect import netem_available, tun_available
from covnet.processes.netem.link import (
    LinkInfo,
    NamespaceError,
    emulated_link,
    namespaces,
    netem_args,
)

__all__ = [
    "LinkInfo",
    "NamespaceError",
    "emulated_link",
    "namespaces",
    "netem_args",
    "netem_available",
    "tun_available",
]
