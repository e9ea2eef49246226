"""What this machine offers for a real emulated link: ``tc netem`` and TUN devices.

Both probes are side-effect free: the netem probe works in a throwaway network namespace that
is always deleted, the TUN probe opens and closes one non-persistent device.
"""

from __future__ import annotations

import fcntl
import os
import shutil
import struct
import subprocess

TUN_PATH = "/dev/net/tun"
TUNSETIFF = 0x400454CA  #: ioctl number, _IOW('T', 202, int)
IFF_TUN = 0x0001
IFF_NO_PI = 0x1000


def run_ip(*args: str, timeout: float = 20.0) -> subprocess.CompletedProcess[str]:
    """``ip ARGS`` with its output captured (never raises on a non-zero exit)."""
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=timeout)


def check_ip(*args: str) -> None:
    """``ip ARGS``; a ``RuntimeError`` with ``ip``'s message when it fails."""
    r = run_ip(*args)
    if r.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)} failed: {r.stderr.strip()}")


def open_tun(name: str) -> int:
    """Create the TUN device ``name`` (IFF_TUN | IFF_NO_PI: bare IP packets) in this process's
    network namespace and return its fd; the device disappears when the fd is closed."""
    fd = os.open(TUN_PATH, os.O_RDWR)
    try:
        fcntl.ioctl(fd, TUNSETIFF, struct.pack("16sH", name.encode(), IFF_TUN | IFF_NO_PI))
    except OSError:
        os.close(fd)
        raise
    return fd


def can_make_namespaces() -> bool:
    """Root and iproute2: what ``ip netns add`` needs (whether it works is tried by callers)."""
    return os.geteuid() == 0 and shutil.which("ip") is not None


def tun_available() -> bool:
    """True when a TUN device can be created here (``/dev/net/tun`` and CAP_NET_ADMIN)."""
    if not os.path.exists(TUN_PATH):
        return False
    try:
        os.close(open_tun(""))  # the kernel names it (tunN): concurrent probes never collide
    except OSError:
        return False
    return True


def netem_available() -> bool:
    """True when the kernel has the ``netem`` qdisc: ``tc qdisc add dev lo root netem delay 1ms``
    in a throwaway namespace succeeds.  False without root, ``ip`` or ``tc``."""
    if not can_make_namespaces() or shutil.which("tc") is None:
        return False
    ns = f"cvprobe{os.getpid() % 100000}"
    try:  # (the add inside: a Ctrl-C while it ran left the namespace behind)
        if run_ip("netns", "add", ns).returncode != 0:
            return False
        r = run_ip("netns", "exec", ns, "tc", "qdisc", "add", "dev", "lo", "root", "netem",
                   "delay", "1ms")  # fmt: skip
        return r.returncode == 0
    finally:
        run_ip("netns", "del", ns)
