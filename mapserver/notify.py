"""systemd notification (``sd_notify``) over ``$NOTIFY_SOCKET``, without a dependency.

The protocol is one datagram of ``KEY=value`` lines to the unix socket named by ``NOTIFY_SOCKET``
(a leading ``@`` means the abstract namespace). Outside systemd the variable is unset and every
call is a no-op.
"""

from __future__ import annotations

import os
import socket

__all__ = ["notify", "watchdog_period"]


def notify(*fields: str) -> bool:
    """Send ``fields`` (``"READY=1"``, ``"STATUS=..."``) to systemd. False when not under systemd or
    when the socket cannot be reached: a notification is never worth crashing for."""
    address = os.environ.get("NOTIFY_SOCKET")
    if not address or not fields:
        return False
    if address.startswith("@"):
        address = "\0" + address[1:]
    message = "\n".join(f.replace("\n", " ") for f in fields).encode("utf-8", "replace")
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            sock.connect(address)
            sock.sendall(message)
    except OSError:
        return False
    return True


def watchdog_period() -> float | None:
    """Seconds within which systemd expects ``WATCHDOG=1`` (``WatchdogSec``), or None when the
    watchdog is off or meant for another process."""
    usec = os.environ.get("WATCHDOG_USEC")
    pid = os.environ.get("WATCHDOG_PID")
    if not usec:
        return None
    try:
        if pid and int(pid) != os.getpid():
            return None
        period = int(usec) / 1e6
    except ValueError:
        return None
    return period if period > 0 else None
