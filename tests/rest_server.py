"""A REST server for the security tests, in its own process (so its memory can be measured alone).

The real API (create_app with RequestGuard), real calibration jobs, a real audit
log and uvicorn; the daemon's other parts are replaced by a small in-memory state
(recordings are names, a shot returns a name, the camera is a black frame every 0.1 s).

    python tests/rest_server.py --port P --work DIR --token T [--api-json '{"max_recordings": 1}']
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
import uvicorn

from drillnav.service.api import create_app, uvicorn_ssl_kwargs
from drillnav.service.audit import AuditLog
from drillnav.service.calibration_jobs import CalibrationJobs
from drillnav.service.settings import ApiSettings


class SmallState:
    def __init__(self, token: str, jobs: CalibrationJobs) -> None:
        self.token, self.calibration_jobs = token, jobs
        self.running: dict[str, list[str]] = {}
        self.refreshes = 0

    def status(self):
        return {"recordings": list(self.running), "refreshes": self.refreshes}

    def health(self):
        return None  # streams flowing: /health answers 200 (the test server has no streams to stall)

    def registration(self):
        return None

    def request_registration(self):
        self.refreshes += 1

    def start_recording(self, name):
        if name in self.running:
            raise KeyError(f"recording '{name}' is already running")
        self.running[name] = [f"{name}-0.mcap"]
        return self.running[name]

    def stop_recording(self, name):
        if name not in self.running:
            raise KeyError(f"no running recording named '{name}'")
        return self.running.pop(name)

    def recordings(self):
        return dict(self.running)

    def shoot(self, view):
        return f"{view}.dcm"


BYTES_READ = [0]


def counting_protocol():
    """uvicorn's own HTTP protocol, counting every byte it takes off the sockets (what the server read)."""
    from uvicorn.protocols.http.auto import AutoHTTPProtocol

    class Counting(AutoHTTPProtocol):  # type: ignore[misc, valid-type]
        def data_received(self, data: bytes) -> None:
            BYTES_READ[0] += len(data)
            super().data_received(data)

    return Counting


def grab_frame() -> tuple[int, np.ndarray]:
    time.sleep(0.1)
    return time.time_ns(), np.zeros((48, 64), np.uint8)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--token", required=True)
    ap.add_argument("--api-json", default="{}")
    args = ap.parse_args(argv)
    api = ApiSettings(port=args.port, token=args.token, audit_folder=args.work / "audit", **json.loads(args.api_json))
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s")
    with CalibrationJobs(work_dir=args.work / "cal", grab_frame=grab_frame, max_active=api.max_jobs_running,
                         max_stored=api.max_jobs_stored, expiry_s=api.job_expiry_s) as jobs, AuditLog(folder=api.audit_folder) as audit:
        app = create_app(state=SmallState(api.token, jobs), settings=api, audit=audit)
        app.get("/test/bytes-read")(lambda: {"bytes": BYTES_READ[0]})  # test instrumentation: bytes uvicorn read so far
        uvicorn.run(app, host="127.0.0.1", port=args.port, log_level="warning", http=counting_protocol(), **uvicorn_ssl_kwargs(api))


if __name__ == "__main__":
    main()
