"""``drillnav serve``: the daemon, until SIGTERM or Ctrl-C."""

from __future__ import annotations

import argparse
import signal
import threading
from pathlib import Path

from .daemon import Daemon
from .settings import load_settings

__all__ = ["register"]


def _serve(args: argparse.Namespace) -> int:
    settings = load_settings(Path(args.config) if args.config else None, twin=True if args.twin else None)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    daemon = Daemon(settings)
    print(f"drillnav: starting on {'the digital twin' if settings.twin else 'real devices'} ...", flush=True)
    daemon.start()
    p = settings.zenoh.prefix
    print(
        f"drillnav: running.\n"
        f"  REST API   http://{settings.api.host}:{settings.api.port}/docs  (status: /status, axis: /registration)\n"
        f"  zenoh      {settings.zenoh.mode} listening on {', '.join(settings.zenoh.listen) or '(none)'}\n"
        f"  DICOM      C-STORE to AE {settings.dicom.ae_title} at {settings.dicom.scp_host}:{settings.dicom.scp_port}, or files into {settings.dicom.watch_folder}/\n"
        f"  drill axis {p}/axis/carm    camera {p}/camera/image    overlays {p}/overlay/<view>    status {p}/registration/status\n"
        f"  listen     .venv/bin/drillnav listen drill-axis --connect {settings.zenoh.listen[0] if settings.zenoh.listen else ''}\n"
        f"  recording  {settings.recording.folder}/  (MCAP, opens in Foxglove)\n"
        f"  stop with Ctrl-C or SIGTERM",
        flush=True,
    )
    try:
        stop.wait()
    finally:
        print("drillnav: stopping, closing recordings ...", flush=True)
        daemon.stop()
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("serve", help="run the daemon")
    p.add_argument("--config", help="drillnav.toml")
    p.add_argument("--twin", action="store_true", help="drive it with the digital twin instead of real devices")
    p.set_defaults(func=_serve)
