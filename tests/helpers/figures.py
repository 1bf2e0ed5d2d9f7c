"""Figures as matplotlib drew them: captured at ``savefig`` and checked for what a reader sees."""

from __future__ import annotations

from typing import Any

import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure


def capture_figures(monkeypatch: pytest.MonkeyPatch) -> list[Figure]:
    """Every Figure saved from now on (the list fills as they are saved; they still get written)."""
    figures: list[Figure] = []
    savefig = Figure.savefig

    def keep(self: Figure, *args: Any, **kw: Any) -> None:
        figures.append(self)
        savefig(self, *args, **kw)

    monkeypatch.setattr(Figure, "savefig", keep)
    return figures


def assert_inside(fig: Figure, *artists: Any) -> None:
    """Each artist (title, legend, …) is drawn wholly inside the figure: nothing cut off."""
    canvas = fig.canvas
    assert isinstance(canvas, FigureCanvasAgg)
    renderer = canvas.get_renderer()
    for artist in artists:
        box = artist.get_window_extent(renderer)
        assert box.x0 >= 0 and box.y0 >= 0, (artist, box)
        assert box.x1 <= fig.bbox.width and box.y1 <= fig.bbox.height, (artist, box)
