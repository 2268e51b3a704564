"""Labelled figures: the sheet itself kept pixel for pixel, its labels and its grey scale drawn
around it (stages.imaging.sheets.annotate)."""

from __future__ import annotations

import numpy as np

from stages.imaging.sheets import annotate


def find(big: np.ndarray, small: np.ndarray) -> tuple[int, int]:
    """Where ``small`` lies inside ``big`` (by its first row, then checked whole)."""
    h, w = small.shape[:2]
    for y in range(big.shape[0] - h + 1):
        for x in range(big.shape[1] - w + 1):
            if np.array_equal(big[y : y + h, x : x + w], small):
                return y, x
    raise AssertionError("the sheet is not inside the labelled figure")


def test_labels_and_scale_around_an_unchanged_sheet():
    rng = np.random.default_rng(0)
    sheet = rng.integers(0, 256, (40, 60, 3), dtype=np.uint8)
    plain = annotate(sheet, "a title")
    labelled = annotate(sheet, "a title", columns=["a", "b", "c"], rows=["row one", "row two"], scale=("0", "0.25", "what"))
    for out in (plain, labelled):
        assert out.dtype == np.uint8 and out.shape[2] == 3
    y0, x0 = find(plain, sheet)
    y, x = find(labelled, sheet)
    assert x > x0 == 0 and y > y0 > 0  # row labels to the left, column labels above
    assert (labelled[:y0] < 128).any(), "no title drawn"
    assert (labelled[:y, x:][y0:] < 128).any(), "no column labels drawn"
    assert (labelled[y : y + 40, :x] < 128).any(), "no row labels drawn"
    below = labelled[y + 40 :, :, 0].astype(int)
    ramp = np.linspace(0, 255, 256).round().astype(int)  # black to white, one pixel per level
    found = [
        (r, c) for r in range(below.shape[0]) for c in range(below.shape[1] - 255) if np.array_equal(below[r, c : c + 256], ramp)
    ]
    assert found, "no black-to-white scale under the sheet"
    assert (labelled[y + 40 :][:, :, 0] == labelled[y + 40 :][:, :, 2]).all()  # grey, and black text
