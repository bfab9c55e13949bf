"""Heat-map pictures of labelled matrices (likelihood matrices: rows = open-set labels, columns = classes).

Drawn with OpenCV only: row names on the left, column names written vertically on top, a viridis colour
scale with ticks on the right, and each cell's value printed where it is large enough to matter. Sized to
be read at 100% zoom (a 38 x 20 likelihood gives about 1100 x 1150 pixels).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

FONT = cv2.FONT_HERSHEY_SIMPLEX
CELL_W, CELL_H = 40, 24  # pixels of one matrix cell
NAME_SCALE, VALUE_SCALE = 0.45, 0.36
MARGIN = 12
BAR_W = 22  # width of the colour scale


def _text_size(text: str, scale: float, thickness: int = 1) -> tuple[int, int]:
    (w, h), baseline = cv2.getTextSize(text, FONT, scale, thickness)
    return w, h + baseline


def _format_value(value: float) -> str:
    """Two significant digits without the leading zero, so a value fits in a cell (`.12`, `1.0`)."""
    if value >= 0.995:
        return f"{value:.1f}" if value < 9.95 else f"{value:.0f}"
    return f"{value:.2f}".lstrip("0")


def heatmap_image(
    matrix: np.ndarray,
    row_names: Sequence[str],
    column_names: Sequence[str],
    title: str = "",
    vmax: float | None = None,
    min_printed: float = 0.05,
) -> np.ndarray:
    """The heat map of `matrix` as an `(H, W, 3)` uint8 BGR image.

    Args:
      matrix: `(R, K)` non-negative values.
      row_names, column_names: `R` and `K` names.
      title: a line above the picture.
      vmax: value at the top of the colour scale (default: the matrix maximum, at least 1e-9).
      min_printed: cells below this value are coloured but not printed (the statistical matrix is
        mostly zeros and near-zeros, whose figures would only be noise to read).
    """
    matrix = np.asarray(matrix, np.float64)
    rows, cols = matrix.shape
    if (len(row_names), len(column_names)) != (rows, cols):
        raise ValueError(f"matrix {matrix.shape} with {len(row_names)} row and {len(column_names)} column names")
    vmax = float(vmax) if vmax is not None else max(float(np.nanmax(matrix)) if matrix.size else 0.0, 1e-9)

    row_w = max((_text_size(name, NAME_SCALE)[0] for name in row_names), default=0) + 8
    col_h = max((_text_size(name, NAME_SCALE)[0] for name in column_names), default=0) + 8
    title_h = _text_size(title, 0.55)[1] + 10 if title else 0
    tick_w = _text_size(_format_value(vmax), NAME_SCALE)[0] + 10
    grid_x, grid_y = MARGIN + row_w, MARGIN + title_h + col_h
    width = grid_x + cols * CELL_W + MARGIN + BAR_W + tick_w + MARGIN
    height = grid_y + rows * CELL_H + MARGIN
    image = np.full((height, width, 3), 255, np.uint8)

    if title:
        cv2.putText(image, title, (MARGIN, MARGIN + title_h - 10), FONT, 0.55, (0, 0, 0), 1, cv2.LINE_AA)

    # Cells: viridis of the value scaled to [0, 255].
    levels = np.clip(np.nan_to_num(matrix) / vmax, 0.0, 1.0)
    colours = cv2.applyColorMap(np.round(levels * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
    image[grid_y : grid_y + rows * CELL_H, grid_x : grid_x + cols * CELL_W] = np.repeat(
        np.repeat(colours, CELL_H, axis=0), CELL_W, axis=1
    )
    for r in range(rows):
        for c in range(cols):
            value = matrix[r, c]
            if not np.isfinite(value) or value < min_printed:
                continue
            text = _format_value(value)
            w, h = _text_size(text, VALUE_SCALE)
            ink = (0, 0, 0) if levels[r, c] > 0.6 else (255, 255, 255)  # dark on the yellow end
            origin = (grid_x + c * CELL_W + (CELL_W - w) // 2, grid_y + r * CELL_H + (CELL_H + h) // 2 - 3)
            cv2.putText(image, text, origin, FONT, VALUE_SCALE, ink, 1, cv2.LINE_AA)
    # Light grid lines every 5 rows and columns help following a row across the picture.
    for r in range(0, rows + 1, 5):
        cv2.line(image, (grid_x, grid_y + r * CELL_H), (grid_x + cols * CELL_W - 1, grid_y + r * CELL_H), (200, 200, 200), 1)
    for c in range(0, cols + 1, 5):
        cv2.line(image, (grid_x + c * CELL_W, grid_y), (grid_x + c * CELL_W, grid_y + rows * CELL_H - 1), (200, 200, 200), 1)

    # Row names, right-aligned against the grid.
    for r, name in enumerate(row_names):
        w, h = _text_size(name, NAME_SCALE)
        cv2.putText(
            image,
            name,
            (grid_x - 6 - w, grid_y + r * CELL_H + (CELL_H + h) // 2 - 3),
            FONT,
            NAME_SCALE,
            (0, 0, 0),
            1,
            cv2.LINE_AA,
        )
    # Column names: written horizontally on a strip, then turned a quarter to read bottom-up.
    strip = np.full((CELL_W * cols, col_h, 3), 255, np.uint8)
    for c, name in enumerate(column_names):
        w, h = _text_size(name, NAME_SCALE)
        cv2.putText(strip, name, (4, c * CELL_W + (CELL_W + h) // 2 - 3), FONT, NAME_SCALE, (0, 0, 0), 1, cv2.LINE_AA)
    image[grid_y - col_h : grid_y, grid_x : grid_x + cols * CELL_W] = np.rot90(strip, k=1)

    # Colour scale with ticks at 0, vmax/2 and vmax.
    bar_x, bar_h = grid_x + cols * CELL_W + MARGIN, rows * CELL_H
    ramp = np.linspace(255, 0, bar_h).round().astype(np.uint8)[:, None]
    image[grid_y : grid_y + bar_h, bar_x : bar_x + BAR_W] = cv2.applyColorMap(
        np.repeat(ramp, BAR_W, axis=1), cv2.COLORMAP_VIRIDIS
    )
    for fraction in (0.0, 0.5, 1.0):
        y = grid_y + int(round((1.0 - fraction) * (bar_h - 1)))
        cv2.line(image, (bar_x + BAR_W, y), (bar_x + BAR_W + 4, y), (0, 0, 0), 1)
        h = _text_size("0", NAME_SCALE)[1]
        y_text = min(max(y + h // 2 - 2, grid_y + h), grid_y + bar_h)
        cv2.putText(
            image,
            _format_value(fraction * vmax) if fraction else "0",
            (bar_x + BAR_W + 6, y_text),
            FONT,
            NAME_SCALE,
            (0, 0, 0),
            1,
            cv2.LINE_AA,
        )
    return image


def write_heatmap(
    path: str | Path,
    matrix: np.ndarray,
    row_names: Sequence[str],
    column_names: Sequence[str],
    title: str = "",
    vmax: float | None = None,
    min_printed: float = 0.05,
) -> np.ndarray:
    """Writes `heatmap_image(...)` as a PNG at `path`; returns the image."""
    image = heatmap_image(matrix, row_names, column_names, title, vmax, min_printed)
    path = Path(path)
    if not cv2.imwrite(str(path), image):
        raise OSError(f"cannot write {path}")
    return image
