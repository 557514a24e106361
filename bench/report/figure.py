"""The one figure helper of every report: matplotlib's object API on the Agg canvas.

No pyplot state: a figure is created here, drawn by its caller, then written
to a PNG file (:func:`save_png`) or to PNG bytes for embedding
(:func:`png_bytes`). matplotlib is imported only when a figure is made.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from matplotlib.figure import Figure

#: Width of every figure [inch].
WIDTH_IN = 8.0
#: Resolution of written figures [dots per inch].
DPI = 100


def new_figure(height_in: float = 3.2, width_in: float = WIDTH_IN) -> Figure:
    """An empty figure of ``width_in`` x ``height_in`` inches on the Agg canvas, constrained layout."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def save_png(fig: Figure, path: str | Path, dpi: float = DPI) -> Path:
    """Write ``fig`` to the PNG file ``path``; return the path."""
    fig.savefig(path, dpi=dpi)
    return Path(path)


def png_bytes(fig: Figure, dpi: float = DPI) -> bytes:
    """``fig`` rendered as PNG bytes (for a report that embeds its images)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()
