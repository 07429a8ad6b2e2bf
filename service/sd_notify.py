"""systemd's notify protocol (``Type=notify``), over ``$NOTIFY_SOCKET`` with a plain datagram socket: no dependency.

``notify("READY=1")`` once the daemon is up, ``notify("WATCHDOG=1")`` at half
of ``WatchdogSec`` while it is healthy (so a wedged daemon is restarted),
``notify("STOPPING=1")`` as it stops. Outside systemd (no ``$NOTIFY_SOCKET``)
every call is a no-op that returns False.
"""

from __future__ import annotations

import os
import socket

__all__ = ["notify", "watchdog_period_s"]


def _address(raw: str) -> str | bytes:
    # '@name' is a Linux abstract socket: its address starts with a NUL byte.
    return b"\0" + raw[1:].encode() if raw.startswith("@") else raw


def notify(state: str, *, socket_path: str | None = None) -> bool:
    """Send ``state`` (``KEY=value`` lines) to systemd; True when sent. Never raises: a lost notification is systemd's to notice."""
    raw = socket_path if socket_path is not None else os.environ.get("NOTIFY_SOCKET", "")
    if not raw:
        return False
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            sock.connect(_address(raw))
            sock.sendall(state.encode())
        return True
    except OSError:
        return False


def watchdog_period_s() -> float | None:
    """How often to send ``WATCHDOG=1`` (half of ``$WATCHDOG_USEC``), or None when systemd asked for no watchdog.

    ``$WATCHDOG_PID``, when set, names the process meant; another process (a child) sends none.
    """
    usec = os.environ.get("WATCHDOG_USEC", "")
    pid = os.environ.get("WATCHDOG_PID", "")
    if not usec.isdigit() or int(usec) == 0 or (pid.isdigit() and int(pid) != os.getpid()):
        return None
    return int(usec) / 2e6
