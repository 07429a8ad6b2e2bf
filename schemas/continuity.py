"""Client-side check that an axis stream arrives whole, in order, and from the registration the client thinks.

Every published ``drillnav.DrillAxis`` carries ``sequence`` (0 for the first
axis a daemon publishes on that key, +1 per axis) and ``registration_id`` (and
``ct_registration_id`` in the video-CT mode). A display that draws the axis
should know when it missed some (a gap), when one arrives late (reordered: an
older axis than the one on screen, not to be drawn), when the daemon restarted
(the sequence back to 0), and when the registration changed under it (a new
shot: the line may jump on purpose). :class:`AxisContinuity` tells it, one
report per message::

    check = AxisContinuity()
    def on_axis(sample):
        axis = json.loads(sample.payload.to_bytes())
        report = check.feed(axis)
        if not report.current:
            return                      # late or repeated: the screen holds a newer axis
        if report.events:
            warn(report.describe())     # e.g. "3 axes missed (41-43)"
        draw(axis)

One instance per stream (key). Standard library only, so a client needs
nothing of drillnav beyond this file.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

__all__ = ["ContinuityEvent", "ContinuityReport", "ContinuityTotals", "AxisContinuity"]


class ContinuityEvent(str, Enum):
    GAP = "gap"                                        # sequence numbers skipped since the newest one seen
    REORDERED = "reordered"                            # an older, missed axis arrived after a newer one
    DUPLICATE = "duplicate"                            # a sequence number seen already
    RESTART = "restart"                                # the sequence went back to 0: the publisher restarted
    REGISTRATION_CHANGED = "registration_changed"      # registration_id (or ct_registration_id) differs from the last


@dataclass(frozen=True)
class ContinuityReport:
    """What one axis message says about the stream."""

    sequence: int
    registration: tuple[int | None, int | None]     # (registration_id, ct_registration_id) of this message
    events: tuple[ContinuityEvent, ...] = ()
    missed: tuple[int, int] | None = None           # GAP: the first and last sequence number skipped
    previous_registration: tuple[int | None, int | None] | None = None  # REGISTRATION_CHANGED: what it was
    current: bool = True                            # False: older than (or equal to) the newest seen; do not draw

    @property
    def missed_count(self) -> int:
        return 0 if self.missed is None else self.missed[1] - self.missed[0] + 1

    def describe(self) -> str:
        """One line for a log or a status bar; empty when the message continues the stream."""
        parts = []
        for e in self.events:
            if e is ContinuityEvent.GAP:
                lo, hi = self.missed  # type: ignore[misc]
                parts.append(f"{self.missed_count} ax{'is' if self.missed_count == 1 else 'es'} missed ({lo}-{hi})" if hi > lo else f"1 axis missed ({lo})")
            elif e is ContinuityEvent.REORDERED:
                parts.append(f"axis {self.sequence} arrived late")
            elif e is ContinuityEvent.DUPLICATE:
                parts.append(f"axis {self.sequence} arrived twice")
            elif e is ContinuityEvent.RESTART:
                parts.append("the publisher restarted (sequence back to 0)")
            elif e is ContinuityEvent.REGISTRATION_CHANGED:
                parts.append(f"registration changed from {_reg(self.previous_registration)} to {_reg(self.registration)}")
        return "; ".join(parts)


def _reg(r: tuple[int | None, int | None] | None) -> str:
    if r is None:
        return "none"
    return str(r[0]) if r[1] is None else f"{r[0]} (CT {r[1]})"


@dataclass
class ContinuityTotals:
    """Running counts over the stream, for a status display."""

    received: int = 0
    missed: int = 0          # skipped and never arrived since (late arrivals are taken back off)
    reordered: int = 0
    duplicates: int = 0
    restarts: int = 0
    registration_changes: int = 0


def _int_field(axis: Mapping[str, Any], name: str, *, required: bool) -> int | None:
    value = axis.get(name)
    if value is None and not required:
        return None
    # bool is an int to Python but never a sequence number; a float 3.0 would hide a producer bug
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"axis message field '{name}' must be an integer, got {value!r}")
    if value < 0:
        raise ValueError(f"axis message field '{name}' must not be negative, got {value}")
    return value


@dataclass
class AxisContinuity:
    """Feed each decoded axis message (a dict) of one stream, in arrival order, to :meth:`feed`.

    ``window`` bounds how many recently missed sequence numbers are remembered
    to recognise a late arrival (older ones count as duplicates if they come).
    """

    window: int = 4096
    totals: ContinuityTotals = field(default_factory=ContinuityTotals)
    _newest: int | None = field(default=None, init=False)
    _newest_stamp: int | None = field(default=None, init=False)
    _registration: tuple[int | None, int | None] | None = field(default=None, init=False)
    _missing: set[int] = field(default_factory=set, init=False)

    def __post_init__(self) -> None:
        if self.window < 1:
            raise ValueError(f"window must be at least 1, got {self.window}")

    def feed(self, axis: Mapping[str, Any]) -> ContinuityReport:
        """The report for one message; ValueError when it has no usable ``sequence`` or ``registration_id``."""
        if not isinstance(axis, Mapping):
            raise ValueError(f"an axis message is a JSON object (dict), got {type(axis).__name__}")
        seq = _int_field(axis, "sequence", required=True)
        reg = (_int_field(axis, "registration_id", required=True), _int_field(axis, "ct_registration_id", required=False))
        stamp = _int_field(axis, "stamp_ns", required=False)
        assert seq is not None
        self.totals.received += 1
        events: list[ContinuityEvent] = []
        newest = self._newest

        if newest is not None and seq <= newest and self._restarted(seq, reg, stamp):
            events.append(ContinuityEvent.RESTART)
            self.totals.restarts += 1
            self._missing.clear()
            newest = None
        if newest is not None and seq <= newest:
            if seq in self._missing:
                self._missing.discard(seq)
                self.totals.reordered += 1
                self.totals.missed -= 1
                events.append(ContinuityEvent.REORDERED)
            else:
                self.totals.duplicates += 1
                events.append(ContinuityEvent.DUPLICATE)
            return ContinuityReport(sequence=seq, registration=reg, events=tuple(events), current=False)

        # the first axis a client sees may be any number (it joined late); after a restart the stream owes 0 onwards
        expected = None if newest is None and not events else (0 if newest is None else newest + 1)
        missed = None
        if expected is not None and seq > expected:
            missed = (expected, seq - 1)
            self.totals.missed += seq - expected
            events.append(ContinuityEvent.GAP)
            self._missing.update(range(max(expected, seq - self.window), seq))
        self._newest, self._newest_stamp = seq, stamp
        self._missing = {m for m in self._missing if m > seq - self.window}
        previous = self._registration
        if previous is not None and reg != previous:
            events.append(ContinuityEvent.REGISTRATION_CHANGED)
            self.totals.registration_changes += 1
        self._registration = reg
        return ContinuityReport(
            sequence=seq, registration=reg, events=tuple(events), missed=missed,
            previous_registration=previous if ContinuityEvent.REGISTRATION_CHANGED in events else None,
        )

    def _restarted(self, seq: int, reg: tuple[int | None, int | None], stamp: int | None) -> bool:
        """A sequence number not above the newest: a restarted publisher, or an old message arriving late?"""
        if stamp is not None and self._newest_stamp is not None:
            # a restart's axes are newer than anything seen; a late or repeated axis is not (even if axis 0 was lost)
            return stamp > self._newest_stamp
        # without stamps only a return to 0 tells, unless it repeats the 0 just seen
        return seq == 0 and not (self._newest == 0 and reg == self._registration)
