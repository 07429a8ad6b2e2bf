"""Live video-CT: keeps ``carm_from_ct`` registered and carries every drill axis into the CT.

The registration node hands each new set of fluoroscopy shots to
:meth:`CtTracker.submit`; the CT registration (seconds) runs in a worker
process of its own (spawned, with one DRR thread at a lower OS priority), so
its CMA-ES never holds the daemon's GIL and the camera loop keeps its pace.
A new shot while one runs is queued (the newest wins). The first registration
starts from the positioner geometry and the plan's entry at the isocentre
(with the translation pre-alignment); later ones start from the last result,
since the patient moves little between shots. A registration that does not
converge keeps the last good ``carm_from_ct`` and says so in an event; a
worker that dies is restarted for the next submission.

:meth:`axis_message` gives ``L_V = ct_from_carm @ L_C`` for each camera frame,
with conformance against the nearest planned trajectory, refreshed at most
every ``conformance_period_s`` (its distance-map look-ups are cheap, but not
free at camera rate).
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drillnav.registration.ct_registration import CtRegistration, register_ct
from drillnav.registration.drr import drr_pyramid
from drillnav.registration.errors import DrillnavError
from drillnav.registration.line import Line3D
from drillnav.registration.transforms import invert
from drillnav.registration.volume import Volume

from drillnav.schemas import messages as msg

from .ct_mode import PlanEntry, acceptance_surface, initial_carm_from_ct, judge_conformance, shots_for_ct

__all__ = ["CtTracker"]


class CtTracker:
    def __init__(
        self,
        *,
        ct: Volume,
        plan: list[PlanEntry],
        at_isocentre_mm: NDArray[np.float64] | None = None,
        on_event: Callable[[str, str], None] = lambda level, message: None,
        search_mm: float = 120.0,
        conformance_period_s: float = 0.2,
    ) -> None:
        self.ct, self.plan, self.on_event = ct, plan, on_event
        self.search_mm, self.conformance_period_s = search_mm, conformance_period_s
        at = at_isocentre_mm if at_isocentre_mm is not None else (plan[0].trajectory.entry_mm if plan else None)
        self.initial = initial_carm_from_ct(ct, at_isocentre_mm=at)
        self._worker: multiprocessing.process.BaseProcess | None = None
        self._conn: Connection | None = None
        self._surfaces: dict = {}
        for entry in plan:  # distance maps up front: none is built at camera rate
            acceptance_surface(ct, entry, self._surfaces)
        if plan:  # and the compiled look-ups loaded before the first frame needs them
            t = plan[0].trajectory
            self._conformance(Line3D(point_mm=np.asarray(t.entry_mm, dtype=np.float64), direction=np.asarray(t.target_mm) - np.asarray(t.entry_mm)))
        self.registration: CtRegistration | None = None
        self._current: tuple[CtRegistration, NDArray[np.float64]] | None = None
        self.registration_id = 0
        self.failures = 0
        self.last_error: str | None = None
        self._pending: tuple[list, int] | None = None
        self._lock = threading.Condition()
        self._stop = threading.Event()
        self._conf: msg.Conformance | None = None
        self._conf_time = 0.0
        self._conf_registration = -1
        self._thread = threading.Thread(target=self._loop, name="ct-registration", daemon=True)
        self._thread.start()

    # -- registration (own thread) ---------------------------------------------------------------
    def submit(self, shots: list[tuple[Any, NDArray[np.float32], Any]], marker_registration_id: int) -> None:
        """``(view, image_log, detections)`` per shot; replaces any submission still waiting."""
        with self._lock:
            self._pending = (shots, marker_registration_id)
            self._lock.notify_all()

    @property
    def worker_pid(self) -> int | None:
        """The registration worker's process id (None before the first registration)."""
        return self._worker.pid if self._worker is not None and self._worker.is_alive() else None

    @property
    def busy(self) -> bool:
        return self._pending is not None

    def _loop(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                while self._pending is None and not self._stop.is_set():
                    self._lock.wait(0.2)
                if self._stop.is_set():
                    return
                shots, marker_id = self._pending
            try:
                self._register(shots, marker_id)
            except _WorkerStopped:
                return
            except (DrillnavError, ValueError) as exc:
                self.failures += 1
                self.last_error = str(exc)
                self.on_event("error", f"CT registration failed: {exc}")
            finally:
                with self._lock:
                    if self._pending is not None and self._pending[0] is shots:
                        self._pending = None

    def _register(self, shots, marker_id: int) -> None:
        previous = self.registration
        start = previous.carm_from_ct if previous is not None else self.initial
        reg = self._in_worker(shots_for_ct(shots), start, None if previous is not None else self.search_mm)
        if not reg.converged:
            self.failures += 1
            self.last_error = f"CT registration did not converge (GC {reg.similarity:.3f})" + ("; keeping the previous one" if previous else "")
            self.on_event("warning", self.last_error)
            return
        self.registration = reg
        self._current = (reg, invert(reg.carm_from_ct))  # one reference, swapped at once for the frame thread
        self.registration_id += 1
        self.last_error = None
        self.on_event("info", f"CT registration {self.registration_id} (after marker registration {marker_id}): GC {reg.similarity:.3f} in {reg.runtime_s:.1f} s")

    def _in_worker(self, shots: list, start: NDArray[np.float64], search_mm: float | None) -> CtRegistration:
        if self._worker is None or not self._worker.is_alive():
            ctx = multiprocessing.get_context("spawn")  # never fork a process that runs zenoh's threads
            self._conn, child = ctx.Pipe()
            self._worker = ctx.Process(target=_worker_main, args=(child, self.ct), name="drillnav-ct-registration", daemon=True)
            self._worker.start()
            child.close()
        assert self._conn is not None
        try:
            self._conn.send((shots, start, search_mm))
        except OSError:  # the worker went between the check and the send: the same death, said the same way
            self._worker.join(timeout=5)
            raise DrillnavError(f"the CT registration worker died (exit code {self._worker.exitcode}); it restarts with the next shot") from None
        while not self._conn.poll(0.2):
            if self._stop.is_set():
                raise _WorkerStopped
            if not self._worker.is_alive():
                raise DrillnavError(f"the CT registration worker died (exit code {self._worker.exitcode}); it restarts with the next shot")
        try:
            kind, value = self._conn.recv()
        except EOFError:  # its end of the pipe closed: it died
            self._worker.join(timeout=5)
            raise DrillnavError(f"the CT registration worker died (exit code {self._worker.exitcode}); it restarts with the next shot") from None
        if kind == "error":
            raise DrillnavError(value)
        return value

    # -- per camera frame ----------------------------------------------------------------------------
    def axis_message(self, axis_carm: Line3D, *, stamp_ns: int, source_frame_stamp_ns: int, predicted_error: msg.PredictedError,
                     registration_id: int, sequence: int) -> msg.DrillAxis | None:
        """The drill axis in frame V (None before the first CT registration)."""
        if self._current is None:
            return None
        reg, ct_from_carm = self._current
        axis_ct = axis_carm.transformed(ct_from_carm)
        now = time.monotonic()
        if self._conf is None or self._conf_registration != self.registration_id or now - self._conf_time > self.conformance_period_s:
            self._conf = self._conformance(axis_ct)
            self._conf_time, self._conf_registration = now, self.registration_id
        return msg.DrillAxis(
            stamp_ns=stamp_ns, frame_id="ct", **msg.drill_axis_fields(point_mm=axis_ct.point_mm, direction=axis_ct.direction, carm_from_ct=reg.carm_from_ct),
            predicted_error=predicted_error, source_frame_stamp_ns=source_frame_stamp_ns, registration_id=registration_id, sequence=sequence,
            ct_registration_id=self.registration_id, ct_similarity_gc=float(reg.similarity), conformance=self._conf,
        )

    def _conformance(self, axis_ct: Line3D) -> msg.Conformance | None:
        """Against the nearest trajectory within the judged angle (None when none is)."""
        judged = judge_conformance(self.ct, axis_ct, self.plan, self._surfaces, nearest_only=True)
        if not judged:
            return None
        j = judged[0]
        where = j.min_clearance_where(axis_ct)  # for the display: mm along the axis from its entry into bone, and the point in V
        return msg.Conformance(trajectory=j.trajectory, axis_to_planned_entry_mm=j.axis_to_planned_entry_mm, angle_to_plan_deg=j.angle_to_plan_deg,
                               breach=j.breach, min_clearance_mm=j.min_clearance_mm, kwire_radius_mm=j.kwire_radius_mm,
                               min_clearance_along_mm=where[0] if where else None, min_clearance_point_mm=where[1] if where else None)

    def status(self) -> dict[str, Any]:
        reg = self.registration
        return {"ct_registration_id": self.registration_id, "ct_registering": self.busy, "ct_failures": self.failures,
                "ct_similarity_gc": None if reg is None else reg.similarity, "ct_last_error": self.last_error}

    def close(self) -> None:
        self._stop.set()
        with self._lock:
            self._lock.notify_all()
        self._thread.join(timeout=2)  # a daemon thread: the exit does not wait on a registration
        if self._worker is not None:
            if self._worker.is_alive():
                self._worker.terminate()  # a registration mid-way has nothing worth keeping
            self._worker.join(timeout=10)
            assert self._conn is not None
            self._conn.close()


class _WorkerStopped(Exception):
    """The tracker is closing while a registration runs."""


def _worker_main(conn: Connection, ct: Volume) -> None:
    """The worker process: builds the DRR pyramid once, then registers each ``(shots, start, search_mm)`` it is sent."""
    try:
        os.nice(10)  # background work, before any thread starts (Linux threads inherit it): the camera loop keeps its core
    except (AttributeError, OSError):
        pass  # no nice here: it competes on equal terms
    import numba

    numba.set_num_threads(1)
    pyramid = drr_pyramid(ct, (1, 2, 4))  # one view ends on the full-resolution volume
    while True:
        try:
            shots, start, search_mm = conn.recv()
        except EOFError:
            return  # the daemon is gone
        try:
            conn.send(("ok", register_ct(pyramid, shots, start, search_mm=search_mm)))
        except (DrillnavError, ValueError) as exc:
            conn.send(("error", str(exc)))
