"""The verification histogram (Figure 7 of the paper): readable as drawn, not only written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure

import service.registrations.histogram as histogram
from tests.helpers.figures import assert_inside, capture_figures


def _drawn_figure(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, **kwargs: object) -> Figure:
    """Write a histogram and return the figure it drew."""
    figures = capture_figures(monkeypatch)
    # the demo's verification: 8 spheres in one bin, 20 in the next (matplotlib ticked 0, 2.5, … 20)
    errors = np.r_[np.full(8, 0.22), np.full(20, 0.27)]
    out = histogram.write_error_histogram(errors, tmp_path / "h.png", **kwargs)
    assert out.is_file() and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    return figures[0]


def test_the_verdict_title_stays_inside_the_figure(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    fig = _drawn_figure(monkeypatch, tmp_path, title="Verification 1: scan 2 vs registration 1", gate_mm=1.0)
    title = fig.axes[0].title
    assert "PASS" in title.get_text() and "gate 1.000 mm" in title.get_text()
    assert_inside(fig, title)


def test_sphere_counts_are_ticked_in_whole_numbers(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    fig = _drawn_figure(monkeypatch, tmp_path, gate_mm=1.0)
    ticks = fig.axes[0].get_yticks()
    assert len(ticks) >= 2 and np.allclose(ticks, np.round(ticks)), ticks
