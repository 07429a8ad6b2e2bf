"""The error hierarchy shared by every drillnav package.

One base class, :class:`DrillnavError`, with typed children. The pure math in
``registration`` raises :class:`ValueError` subclasses (``DegenerateInput``) so
that callers who know only numpy conventions still catch them; drivers and the
service raise the device and I/O errors. The service turns any of them into an
HTTP problem or a status message; nothing is printed and swallowed.
"""

from __future__ import annotations

__all__ = [
    "DrillnavError",
    "DegenerateInput",
    "NotConverged",
    "MarkersNotFound",
]


class DrillnavError(Exception):
    """Base of every error drillnav raises on purpose."""


class DegenerateInput(DrillnavError, ValueError):
    """Input that the math cannot use: too few points, collinear, singular, wrong shape."""


class NotConverged(DrillnavError):
    """An optimiser or iterative solve ended without meeting its tolerance."""


class MarkersNotFound(DrillnavError):
    """No usable marker (or too few) was found in an image."""
