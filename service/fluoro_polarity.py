"""A fluoroscopy image whose file does not say which way its values run: the reading in which the markers show.

An image without Pixel Intensity Relationship LIN or LOG (processed for display, DISP) may show metal bright, as a
radiograph's display does, or dark, as most fluoroscopy displays do; the driver reads it both ways
(:attr:`~drillnav.drivers.fluoro_dicom.FluoroImage.alternative_log`). Only the right reading shows the
tungsten BBs as the peaks the marker detector looks for: read the wrong way they are pits. On the operating-room twin
(seeds 5000-5003, 24 views, every fluoroscopy degradation but the CT) the detector identified no marker and no candidate
in any view read the wrong way, against 73 markers read the right way. So the reading with more markers identified is taken; on a
tie (no marker in either) its display's convention (metal bright) stands and the caller is told.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from drillnav.drivers.fluoro_dicom import FluoroImage
from drillnav.registration.fluoro_markers import FluoroDetections, detect_in_view
from drillnav.registration.markers import MarkerSet

__all__ = ["SettledImage", "settle_polarity"]


@dataclass(frozen=True, kw_only=True)
class SettledImage:
    """An image with the reading taken, its markers as the detector found them in it, and what was decided.

    ``note`` is empty where the file stated its polarity; else it names the reading taken and the markers identified
    in each, for the operator's log.
    """

    image: FluoroImage
    detections: FluoroDetections
    note: str = ""


def _identified(det: FluoroDetections) -> int:
    return len(det.markers)


def settle_polarity(image: FluoroImage, marker_set: MarkerSet) -> SettledImage:
    """``image`` as it reads (its markers detected), or, where its file does not state its polarity, in the reading
    in which more of ``marker_set``'s markers are identified (its display's convention, metal bright, on a tie)."""
    first = detect_in_view(image.pixels_log, image.view, marker_set)
    if image.polarity_stated:
        return SettledImage(image=image, detections=first)
    other_image = image.read_the_other_way()
    other = detect_in_view(other_image.pixels_log, other_image.view, marker_set)
    n_first, n_other = _identified(first), _identified(other)
    said = f"{Path(image.source_file).name} frame {image.frame_index}: polarity not stated (no Pixel Intensity Relationship LIN / LOG)"
    if n_other > n_first:
        note = f"{said}: read {image.alternative_reading}, {n_other} marker(s) identified, against {n_first} {image.reading}"
        return SettledImage(image=other_image, detections=other, note=note)
    if n_first > n_other:
        note = f"{said}: read {image.reading}, {n_first} marker(s) identified, against {n_other} {image.alternative_reading}"
    else:
        note = f"{said}: no reading identifies more markers ({n_first} either way): read {image.reading}"
    # Only the reading taken travels on: the other would be a second image of the same shot.
    return SettledImage(image=image.read_as_first(), detections=first, note=note)
