"""A fluoroscopy image whose file does not say which way its values run: the reading in which the markers show.

A MONOCHROME2 image without Pixel Intensity Relationship LIN or LOG (processed for display, DISP) may show metal
bright, as a radiograph's display does, or dark, as most fluoroscopy displays do; the driver reads it both ways
(:attr:`~drillnav.drivers.fluoro_dicom.FluoroImage.pixels_log_as_intensity`). Only the right reading shows the
tungsten BBs as the peaks the marker detector looks for: read the wrong way they are pits, and on the operating-room
twin (36 views, every fluoroscopy degradation but the CT) the detector identified no marker and no candidate in a single
wrongly read view, against 51 markers read the right way. So the reading with more markers identified is taken; on a
tie (no marker in either) the file's MONOCHROME2 convention (metal bright) stands and the caller is told.
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
    """``image`` as it reads (its markers detected), or, where its file does not state its polarity, with the reading
    in which more of ``marker_set``'s markers are identified (the display's own convention, metal bright, on a tie)."""
    as_displayed = detect_in_view(image.pixels_log, image.view, marker_set)
    if image.polarity_stated:
        return SettledImage(image=image, detections=as_displayed)
    flipped = image.read_as_intensity()
    as_intensity = detect_in_view(flipped.pixels_log, flipped.view, marker_set)
    n_displayed, n_intensity = _identified(as_displayed), _identified(as_intensity)
    name = f"{Path(image.source_file).name} frame {image.frame_index}"
    if n_intensity > n_displayed:
        note = (f"{name}: polarity not stated (MONOCHROME2, no LIN / LOG): read as intensity, metal dark "
                f"({n_intensity} marker(s) identified read so, {n_displayed} read metal bright)")
        return SettledImage(image=flipped, detections=as_intensity, note=note)
    if n_displayed > n_intensity:
        note = (f"{name}: polarity not stated (MONOCHROME2, no LIN / LOG): read metal bright "
                f"({n_displayed} marker(s) identified read so, {n_intensity} read as intensity)")
    else:
        note = (f"{name}: polarity not stated (MONOCHROME2, no LIN / LOG) and no reading identifies more markers "
                f"({n_displayed} either way): read metal bright, as MONOCHROME2 displays it")
    # Only the reading taken travels on: the other would be a second image of the same shot.
    return SettledImage(image=image.read_as_displayed(), detections=as_displayed, note=note)
