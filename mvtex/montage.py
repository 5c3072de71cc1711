"""Compose pictures for people: grids of images with labels."""

from __future__ import annotations

from typing import Sequence

import numpy as np


def label(image: np.ndarray, text: str, scale: float = 0.5) -> np.ndarray:
    """A copy of an RGB uint8 image with `text` written in its top-left corner."""
    import cv2

    out = np.ascontiguousarray(image.copy())
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    cv2.rectangle(out, (0, 0), (w + 8, h + base + 8), (0, 0, 0), -1)
    cv2.putText(out, text, (4, h + 4), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def grid_image(rows: Sequence[Sequence[np.ndarray]], col_labels: Sequence[str] | None = None,
               row_labels: Sequence[str] | None = None, gap: int = 4, max_width: int = 3072) -> np.ndarray:
    """Tile RGB uint8 images (all the same size) into one picture, labelled "row / column".

    Wide grids are scaled down to at most `max_width` pixels.
    """
    import cv2

    h, w = rows[0][0].shape[:2]
    ncol = max(len(r) for r in rows)
    canvas = np.full((len(rows) * (h + gap) - gap, ncol * (w + gap) - gap, 3), 255, np.uint8)
    for i, row in enumerate(rows):
        for j, image in enumerate(row):
            text = " / ".join(t for t in ((row_labels[i] if row_labels else ""), (col_labels[j] if col_labels else "")) if t)
            tile = label(image, text) if text else image
            canvas[i * (h + gap):i * (h + gap) + h, j * (w + gap):j * (w + gap) + w] = tile
    if canvas.shape[1] > max_width:
        s = max_width / canvas.shape[1]
        canvas = cv2.resize(canvas, (max_width, int(canvas.shape[0] * s)), interpolation=cv2.INTER_AREA)
    return canvas
