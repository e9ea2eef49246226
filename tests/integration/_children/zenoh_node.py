"""A minimal sensor-like node for the zenoh integration tests (spawned, never imported).

Connects as a zenoh client, subscribes to the run's commands, declares its liveliness token
(after the subscription, as real nodes do), publishes ``--count`` measurements (scans 0..N-1),
prints READY, then answers every command that enables it with a measurement for that scan,
until SIGINT. It waits for commands with ``recv(timeout=None)``: only a signal delivered to the
main thread ends that wait, so a prompt exit on SIGINT shows that zenoh's threads block it.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from covnet.wire import messages as m
from covnet.wire.zenoh_bus import ZenohBus, zenoh_config


def main(connect: str, run: str, node: str, count: int, lease_ms: int | None) -> int:
    config = zenoh_config("client", connect=[connect], lease_ms=lease_ms)
    with ZenohBus.open(config) as bus:
        commands = bus.subscribe(m.command_keyexpr(run, node))  # those that enable it
        bus.declare_token(m.alive_key(run, "sensor", node))
        key = m.measurement_key(run, node)
        R = np.eye(2)
        for scan in range(count):
            z = np.array([[float(scan), -float(scan)]])
            meas = m.Measurement(node, scan, 0.1 * scan, z, R, time.monotonic_ns())
            bus.publish(key, m.encode(meas))
        try:
            print("READY", flush=True)  # inside the try: a SIGINT right after it is caught
            # no `while True: ... continue` inside `try` (CPython #108214 lets a signal raised
            # at that jump escape the `except`); recv(None) blocks until a command or a signal
            while (sample := commands.recv(timeout=None)) is not None:
                cmd = m.decode_command(sample.key, sample.payload)
                if node in cmd.enabled:
                    z = np.array([[float(cmd.scan), 0.5]])
                    meas = m.Measurement(node, cmd.scan, cmd.t, z, R, time.monotonic_ns())
                    bus.publish(key, m.encode(meas))
        except KeyboardInterrupt:
            print("STOPPING", flush=True)
    return 0


if __name__ == "__main__":
    p = argparse.ArgumentParser()
    p.add_argument("--connect", required=True)
    p.add_argument("--run", required=True)
    p.add_argument("--node", required=True)
    p.add_argument("--count", type=int, default=0)
    p.add_argument("--lease-ms", type=int, default=None)
    a = p.parse_args()
    sys.exit(main(a.connect, a.run, a.node, a.count, a.lease_ms))
