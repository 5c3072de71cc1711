"""Pictures: error heatmaps (blue = 0, red >= vmax, dark background), labelled
side-by-side panels and labelled grids."""

from __future__ import annotations

from typing import Sequence

import numpy as np

BACKGROUND = (24, 24, 28)


def heatmap(error: np.ndarray, vmax: float = 0.04, *, background: tuple[int, int, int] = BACKGROUND) -> np.ndarray:
    """Colour a per-pixel error image with matplotlib's "jet" map.

    Args:
        error: (H,W) float; NaN where undefined (drawn as `background`).
        vmax: error drawn fully red (and everything above it); 0 is blue.

    Returns:
        (H,W,3) uint8 RGB.
    """
    from matplotlib import colormaps

    e = np.asarray(error, dtype=np.float64)
    valid = np.isfinite(e)
    x = np.clip(np.where(valid, e, 0.0) / float(vmax), 0.0, 1.0)
    rgb = (colormaps["jet"](x)[..., :3] * 255.0 + 0.5).astype(np.uint8)
    rgb[~valid] = background
    return rgb


def label(image: np.ndarray, text: str, *, scale: float = 0.5) -> np.ndarray:
    """Copy of an RGB uint8 image with `text` written in its top-left corner."""
    import cv2

    out = np.ascontiguousarray(np.asarray(image, dtype=np.uint8).copy())
    thick = max(1, int(round(2 * scale)))
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thick)
    cv2.rectangle(out, (0, 0), (w + 8, h + base + 8), (0, 0, 0), -1)
    cv2.putText(out, text, (4, h + 4), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), thick, cv2.LINE_AA)
    return out


def side_by_side(images: Sequence[np.ndarray], labels: Sequence[str] | None = None, *, gap: int = 4,
                 gap_color: tuple[int, int, int] = (255, 255, 255)) -> np.ndarray:
    """Place RGB uint8 images of equal height left to right, optionally labelled."""
    images = [np.asarray(im, dtype=np.uint8) for im in images]
    if labels is not None:
        images = [label(im, t) if t else im for im, t in zip(images, labels)]
    h = max(im.shape[0] for im in images)
    parts = []
    for i, im in enumerate(images):
        if im.shape[0] != h:
            pad = np.zeros((h - im.shape[0],) + im.shape[1:], np.uint8)
            im = np.concatenate([im, pad])
        if i:
            parts.append(np.broadcast_to(np.array(gap_color, np.uint8), (h, gap, 3)))
        parts.append(im)
    return np.ascontiguousarray(np.concatenate(parts, axis=1))


def colorbar(height: int, vmax: float = 0.04, width: int = 60, unit: str = "") -> np.ndarray:
    """A vertical (height, width, 3) colour bar for `heatmap`, 0 at the bottom, labelled
    (with `unit` under the top value when given)."""
    import cv2

    ramp = np.linspace(vmax, 0.0, height)[:, None] * np.ones((1, width // 3))
    bar = heatmap(ramp, vmax)
    canvas = np.full((height, width, 3), BACKGROUND, np.uint8)
    canvas[:, : bar.shape[1]] = bar
    for value, y in ((vmax, 12), (0.0, height - 4)):
        text = f"{value:g}" + ("+" if value == vmax else "")
        cv2.putText(canvas, text, (bar.shape[1] + 2, y), cv2.FONT_HERSHEY_SIMPLEX, 0.3, (255, 255, 255), 1, cv2.LINE_AA)
    if unit:
        cv2.putText(canvas, unit, (bar.shape[1] + 2, 26), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 255), 1, cv2.LINE_AA)
    return canvas


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
