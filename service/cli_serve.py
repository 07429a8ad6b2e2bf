"""``drillnav serve``: the daemon, until SIGTERM or Ctrl-C.

Start-up prints a progress line per part. A start-up failure is one line on
stderr and exit status 1; SIGTERM or SIGINT at any moment (during start-up
too) stops every part, finalises the recordings and exits 0. Output never
stops the daemon: with stdout closed (``drillnav serve | head -1``) the lines
are dropped. Under systemd (``Type=notify``) it sends ``READY=1`` once up,
``WATCHDOG=1`` while not wedged (:meth:`Daemon.wedged`) and ``STOPPING=1``.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from pathlib import Path

from drillnav.registration.errors import DrillnavError

from . import sd_notify

__all__ = ["register"]

EXIT_FAILURE = 1


class _Interrupted(BaseException):
    """SIGTERM/SIGINT during start-up: unwinds the daemon's ExitStack from wherever start-up is."""


class _Lines:
    """Progress lines on stdout that never raise: a closed pipe turns them off (and fd 1 to /dev/null)."""

    def __init__(self) -> None:
        self.alive = True

    def __call__(self, line: str) -> None:
        if not self.alive:
            return
        try:
            print(f"drillnav: {line}", flush=True)
        except (BrokenPipeError, OSError, ValueError):
            self.alive = False
            # The interpreter flushes stdout once more at exit; with the pipe gone that would fail too.
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)


def _error(line: str) -> None:
    try:
        print(f"drillnav serve: error: {line}", file=sys.stderr, flush=True)
    except OSError:
        pass


def _serve(args: argparse.Namespace) -> int:
    say = _Lines()
    stop = threading.Event()
    starting = True

    def on_signal(signum, _frame) -> None:
        nonlocal starting
        stop.set()
        if starting:  # once only: a second signal must not break off the unwinding the first began
            starting = False
            raise _Interrupted(signal.Signals(signum).name)

    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, on_signal)
    daemon = None
    try:
        from .daemon import Daemon
        from .settings import load_settings

        settings = load_settings(Path(args.config) if args.config else None, twin=True if args.twin else None)
        say(f"starting on {'the digital twin' if settings.twin else 'real devices'} ...")
        daemon = Daemon(settings, progress=say)
        daemon.__enter__()
        starting = False  # from here a signal only sets `stop`
    except _Interrupted as exc:
        if daemon is not None:
            daemon.close()  # a no-op unless the signal came between start-up's end and the line above
        say(f"{exc.args[0]} during start-up: stopped")
        return 0
    except (DrillnavError, ValueError, OSError) as exc:
        _error(str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
        return EXIT_FAILURE
    except Exception as exc:  # noqa: BLE001 - a fault start-up did not foresee is still one line, not a traceback
        _error(f"unexpected {type(exc).__name__} during start-up: {str(exc).splitlines()[0] if str(exc) else ''}")
        return EXIT_FAILURE
    rc = 0
    try:
        _running(settings, say)
        sd_notify.notify("READY=1\nSTATUS=running")
        period = sd_notify.watchdog_period_s()
        first_axis = False
        while not stop.wait(min(period or 0.5, 0.5)):
            if not first_axis and daemon.node.counters.axes_published:
                first_axis = True
                say("first axis published")
            if period is not None and daemon.wedged() is None:
                sd_notify.notify("WATCHDOG=1")  # only while not wedged: a stuck daemon misses its pings and is restarted
    except Exception as exc:  # noqa: BLE001 - whatever it was, the recordings are still finalised below
        _error(f"unexpected {type(exc).__name__}: {exc}")
        rc = EXIT_FAILURE
    finally:
        sd_notify.notify("STOPPING=1")
        say("stopping, closing recordings ...")
        daemon.close()
        say("stopped")
    return rc


def _running(settings, say) -> None:
    p = settings.zenoh.prefix
    for line in (
        "running.",
        f"  REST API   http://{settings.api.host}:{settings.api.port}/docs  (health: /health, status: /status, axis: /registration)",
        f"  drill axis {p}/axis/carm    camera {p}/camera/image    overlays {p}/overlay/<view>    status {p}/registration/status",
        f"  listen     .venv/bin/drillnav listen drill-axis --connect {settings.zenoh.listen[0] if settings.zenoh.listen else ''}",
        f"  DICOM      files into {settings.dicom.watch_folder}/" + (f", or C-STORE to AE {settings.dicom.ae_title} at {settings.dicom.scp_host}:{settings.dicom.scp_port}" if settings.dicom.scp_enabled else ""),
        "  stop with Ctrl-C or SIGTERM",
    ):
        say(line)


def _serve_and_exit(args: argparse.Namespace) -> int:
    """Ends the process itself once the daemon is closed, so no stray thread (a library's, a busy job's) holds the exit."""
    rc = _serve(args)
    try:
        sys.stdout.flush()
        sys.stderr.flush()
    except OSError:
        pass
    os._exit(rc)


def register(subparsers) -> None:
    p = subparsers.add_parser("serve", help="run the daemon")
    p.add_argument("--config", help="drillnav.toml")
    p.add_argument("--twin", action="store_true", help="drive it with the digital twin instead of real devices")
    p.set_defaults(func=_serve_and_exit)
