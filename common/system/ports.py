"""Free loopback ports for routers started on this machine, chosen below the kernel's ephemeral range.

Binding port 0 returns a port of the ephemeral range (``net.ipv4.ip_local_port_range``, 32768-60999
by default), the range the kernel also draws the local port of every outgoing connection from: on a
host opening many connections (a fleet, a parallel test run), a port free when probed can be taken by
a connection before the router binds it, and the router does not start. A port below that range is
never given to an outgoing connection. The C socket type: choosing a port opens no connection, so a
caller that refuses new sockets (tests/tiers.py wraps ``socket.socket``) may still choose one.
"""

from __future__ import annotations

import _socket
import random
from pathlib import Path

LOWEST = 20000  # above the well-known and most registered services' ports
_PICK = random.Random()  # seeded from the OS: parallel workers draw different ports


def _ephemeral_start() -> int:
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768  # Linux's default


def _bound(port: int) -> int:
    sock = _socket.socket(_socket.AF_INET, _socket.SOCK_STREAM)
    try:
        sock.bind(("127.0.0.1", port))
        return int(sock.getsockname()[1])
    finally:
        sock.close()


def free_port() -> int:
    """A loopback TCP port nothing listens on now, below the ephemeral range where it has room."""
    top = _ephemeral_start()
    if top - LOWEST >= 1000:
        for _ in range(100):
            try:
                return _bound(_PICK.randrange(LOWEST, top))
            except OSError:  # in use (or in TIME_WAIT): another
                continue
    return _bound(0)
