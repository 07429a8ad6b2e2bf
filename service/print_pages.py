"""Pages printed at 1:1 (marker sheets, the drill-axis jig): paper sizes, millimetre axes, a scale bar, PDF/SVG output.

Every page is a matplotlib figure the size of the paper whose axes run in
millimetres from the page's bottom-left corner, so what is drawn at ``x`` mm
prints at ``x`` mm. matplotlib sizes lines in points (1/72 inch), never in
data units: :func:`line_width_pt` converts a width in mm. Images are embedded
unresampled (``interpolation="none"``), so a tag's cells stay square and sharp.
matplotlib is imported by the functions: importing this module costs nothing.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .cli import CliError

__all__ = ["PAPER_MM", "PT_PER_MM", "line_width_pt", "new_page", "draw_scale_bar", "save_pages", "SCALE_BAR_MM"]

PAPER_MM: dict[str, tuple[float, float]] = {"A4": (210.0, 297.0), "Letter": (215.9, 279.4)}  # (width, height)
PT_PER_MM = 72.0 / 25.4
SCALE_BAR_MM = 100.0


def line_width_pt(width_mm: float) -> float:
    """matplotlib's ``linewidth`` (points) of a line ``width_mm`` wide on paper."""
    return width_mm * PT_PER_MM


def new_page(paper: str) -> tuple[Any, Any]:
    """(figure, axes) of one ``paper`` page ("A4" or "Letter"), axes in mm from the bottom-left corner."""
    if paper not in PAPER_MM:
        raise CliError(f"unknown paper '{paper}': use {' or '.join(PAPER_MM)}")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    w, h = PAPER_MM[paper]
    fig = plt.figure(figsize=(w / 25.4, h / 25.4))
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_xlim(0, w)
    ax.set_ylim(0, h)
    ax.set_aspect("equal")
    ax.axis("off")
    return fig, ax


def draw_scale_bar(ax, x_mm: float, y_mm: float, *, length_mm: float = SCALE_BAR_MM) -> None:
    """A ``length_mm`` bar from (x, y) to the right, ticks every 10 mm (taller every 50), and how to use it."""
    lw = line_width_pt(0.3)
    ax.plot([x_mm, x_mm + length_mm], [y_mm, y_mm], color="k", lw=lw, solid_capstyle="butt")
    for t in range(0, int(length_mm) + 1, 10):
        tick = 4.0 if t % 50 == 0 else 2.0
        ax.plot([x_mm + t, x_mm + t], [y_mm, y_mm + tick], color="k", lw=lw, solid_capstyle="butt")
    ax.text(x_mm + length_mm / 2, y_mm - 1.5, f"{length_mm:.0f} mm: measure this bar; print at 100 % (no 'fit to page')",
            ha="center", va="top", fontsize=6)


def save_pages(figures: Sequence[Any], out: Path) -> None:
    """Write the pages as one PDF (one page each) or, for a single page, an SVG; closes the figures."""
    import matplotlib.pyplot as plt

    try:
        if out.suffix.lower() == ".pdf":
            from matplotlib.backends.backend_pdf import PdfPages

            with PdfPages(out) as pdf:
                for fig in figures:
                    pdf.savefig(fig)
        elif len(figures) == 1:
            figures[0].savefig(out)
        else:
            raise CliError(f"{len(figures)} pages do not fit one SVG: write a PDF, or print fewer ids")
    finally:
        for fig in figures:
            plt.close(fig)
