"""Pictures for people: colormaps, per-pixel heatmaps and per-vertex error / strain /
texture colours, shaded renders of vertex colours, the gt / inferred / reconstruction
comparison, labelled side-by-side panels and grids.

The one "jet" map (blue = 0, red ≥ vmax) is `colormap(..., "jet")`; heatmaps and error
colours both use it. GL renders go through `mvtex.render.raster`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import numpy as np

from mvtex.data.mesh import vertex_normals, vertex_strain_energy, weld_groups
from mvtex.render.context import context_or_new
from mvtex.render.raster import interpolate, rasterize
from mvtex.render.shading import (
    BODY_RGB,
    CLOTH_RGB,
    _with_body,
    fabric_colors,
    garment_box,
    render_shaded,
    render_textured,
    scaled_camera,
)

if TYPE_CHECKING:
    from mvtex.render.context import GLContext


BACKGROUND = (24, 24, 28)


def colormap(values: np.ndarray, vmin: float, vmax: float, name: str = "jet") -> np.ndarray:
    """Values (...) -> colours (..., 3) uint8 of a matplotlib colormap over [vmin, vmax] (clipped)."""
    from matplotlib import colormaps  # noqa: PLC0415 (loaded on use)

    x = np.clip((np.asarray(values, np.float64) - vmin) / (vmax - vmin), 0.0, 1.0)
    return (colormaps[name](x)[..., :3] * 255.0 + 0.5).astype(np.uint8)


def heatmap(error: np.ndarray, vmax: float | ColorScale = 0.04, *,
            background: tuple[int, int, int] = BACKGROUND) -> np.ndarray:
    """Colour a per-pixel error image with matplotlib's "jet" map.

    Args:
        error: (H,W) float; NaN where undefined (drawn as `background`).
        vmax: a `ColorScale`, or the error drawn fully red (and everything above it), 0
            blue.

    Returns:
        (H,W,3) uint8 RGB.
    """
    e = np.asarray(error, dtype=np.float64)
    valid = np.isfinite(e)
    if isinstance(vmax, ColorScale):
        rgb = vmax.colors(np.where(valid, e, vmax.vmin))
    else:
        rgb = colormap(np.where(valid, e, 0.0), 0.0, float(vmax), "jet")
    rgb[~valid] = background
    return rgb


def label(image: np.ndarray, text: str, *, scale: float = 0.5) -> np.ndarray:
    """Copy of an RGB uint8 image with `text` written in its top-left corner."""
    import cv2  # noqa: PLC0415 (loaded on use)

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


def _text(canvas: np.ndarray, text: str, x: int, y: int, scale: float = 0.4,
          color: tuple[int, int, int] = (235, 235, 235)) -> None:
    import cv2  # noqa: PLC0415 (loaded on use)

    cv2.putText(canvas, text, (int(x), int(y)), cv2.FONT_HERSHEY_SIMPLEX, scale, color, 1, cv2.LINE_AA)


def _vertical_text(text: str, height: int, scale: float = 0.45, background=BACKGROUND) -> np.ndarray:
    """`text` written bottom to top, centred in a (height, h, 3) strip."""
    import cv2  # noqa: PLC0415 (loaded on use)

    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    strip = np.full((h + base + 6, max(height, w + 4), 3), background, np.uint8)
    _text(strip, text, (strip.shape[1] - w) // 2, h + 3, scale)
    strip = np.rot90(strip)  # text now reads bottom to top
    if strip.shape[0] > height:
        c = (strip.shape[0] - height) // 2
        strip = strip[c:c + height]
    return np.ascontiguousarray(strip)


def _nice_up(x: float) -> float:
    """The smallest of 1, 1.2, 1.5, 2, 2.5, 3, 4, 5, 6, 8 times a power of ten that is >= x."""
    if not np.isfinite(x) or x <= 0:
        return 1.0
    e = np.floor(np.log10(x))
    for m in (1, 1.2, 1.5, 2, 2.5, 3, 4, 5, 6, 8, 10):
        if m * 10 ** e >= x * (1 - 1e-12):
            return float(m * 10 ** e)
    return float(10 ** (e + 1))


@dataclass(frozen=True)
class ColorScale:
    """A colour scale: values in [vmin, vmax] to a matplotlib colormap, clipped at both ends,
    linear or logarithmic; `title` and `unit` name its axis, values are shown times `factor`
    (1e3 to show meters as millimeters).

    `fit_scale` chooses one from the data; `colorbar` draws it.
    """

    vmin: float
    vmax: float
    log: bool = False
    name: str = "jet"
    title: str = ""
    unit: str = ""
    factor: float = 1.0

    def normalized(self, values: np.ndarray) -> np.ndarray:
        """Values (...) -> positions in [0, 1] on the scale (clipped; NaN stays NaN)."""
        v = np.asarray(values, np.float64)
        if self.log:
            with np.errstate(divide="ignore", invalid="ignore"):
                x = (np.log10(np.maximum(v, self.vmin)) - np.log10(self.vmin)) / (np.log10(self.vmax) - np.log10(self.vmin))
        else:
            x = (v - self.vmin) / (self.vmax - self.vmin)
        return np.clip(x, 0.0, 1.0)

    def colors(self, values: np.ndarray) -> np.ndarray:
        """Values (...) -> (..., 3) uint8 (NaN drawn as vmin)."""
        from matplotlib import colormaps  # noqa: PLC0415 (loaded on use)

        x = np.nan_to_num(self.normalized(values), nan=0.0)
        return (colormaps[self.name](x)[..., :3] * 255.0 + 0.5).astype(np.uint8)

    @property
    def axis(self) -> str:
        """The axis name with its unit, "material error (mm)"."""
        return f"{self.title} ({self.unit})" if self.unit else self.title

    def to_json(self) -> dict:
        return {"vmin": self.vmin, "vmax": self.vmax, "log": self.log, "colormap": self.name, "title": self.title,
                "unit": self.unit, "factor": self.factor}


def fit_scale(values, *, percentile: float = 99.0, log: bool = True, decades: tuple[float, float] = (1.0, 3.0),
              low_percentile: float = 5.0, title: str = "", unit: str = "", factor: float = 1.0,
              name: str = "jet") -> ColorScale:
    """A colour scale that fits the data: its top is the `percentile` of the finite values
    (all arrays of `values` pooled, so that panels drawn with it compare), rounded up to a
    round number (at most 20 % higher); with `log`, its bottom is the `low_percentile` of
    the positive values, kept between `decades[1]` and `decades[0]` decades below the top
    (so both a large and a small error show their structure on one scale); linear scales
    start at 0.

    Args:
        values: an array or a sequence of arrays (NaN ignored).
    """
    if isinstance(values, np.ndarray):
        values = [values]
    flat = np.concatenate([np.asarray(v, np.float64).ravel() for v in values]) if len(values) else np.zeros(0)
    flat = flat[np.isfinite(flat)]
    top = float(np.percentile(flat, percentile)) if flat.size else 0.0
    if top <= 0:
        top = float(flat.max()) if flat.size and flat.max() > 0 else 1.0
    vmax = _nice_up(top * factor) / factor
    if not log:
        return ColorScale(0.0, vmax, False, name, title, unit, factor)
    positive = flat[flat > 0]
    low = float(np.percentile(positive, low_percentile)) if positive.size else vmax / 10 ** decades[1]
    low = min(max(low, vmax / 10 ** decades[1]), vmax / 10 ** decades[0])
    vmin = 10 ** np.floor(np.log10(low * factor)) / factor
    return ColorScale(float(vmin), float(vmax), True, name, title, unit, factor)


def _label_value(value: float) -> str:
    return f"{value:.3g}"


def colorbar(height: int, vmax: float | ColorScale = 0.04, width: int = 96, unit: str = "") -> np.ndarray:
    """A vertical (height, width, 3) colour bar: the scale's colours bottom (vmin) to top
    (vmax), tick values beside it (the top one "+": values above it are drawn in its
    colour), and the axis name with its unit written along the right edge.

    Args:
        vmax: a `ColorScale`, or (the "jet" map from 0, linear) its top value.
        unit: with a number `vmax`, the axis name.
    """
    scale = vmax if isinstance(vmax, ColorScale) else ColorScale(0.0, float(vmax), title=unit)
    canvas = np.full((height, width, 3), BACKGROUND, np.uint8)
    top, bottom = 10, height - 10
    bar_w = 16
    positions = np.linspace(1.0, 0.0, bottom - top)
    from matplotlib import colormaps  # noqa: PLC0415 (loaded on use)

    ramp = (colormaps[scale.name](positions)[:, :3] * 255 + 0.5).astype(np.uint8)
    canvas[top:bottom, 4:4 + bar_w] = ramp[:, None, :]
    if scale.log:
        lo, hi = np.log10(scale.vmin * scale.factor), np.log10(scale.vmax * scale.factor)
        ticks = [10 ** e for e in range(int(np.ceil(lo)), int(np.floor(hi)) + 1)]
        ticks = sorted({scale.vmin * scale.factor, *ticks, scale.vmax * scale.factor})
    else:
        ticks = [scale.vmin * scale.factor + f * (scale.vmax - scale.vmin) * scale.factor for f in (0, 0.25, 0.5, 0.75, 1)]
    last_y = None
    for t in sorted(ticks, reverse=True):
        x = float(scale.normalized(t / scale.factor))
        y = int(round(bottom - 1 - x * (bottom - top - 1)))
        if last_y is not None and abs(y - last_y) < 16:
            continue
        canvas[y, 4 + bar_w:8 + bar_w] = 235
        text = _label_value(t) + ("+" if np.isclose(t, scale.vmax * scale.factor) else "")
        _text(canvas, text, 10 + bar_w, min(max(y + 4, 10), height - 2), 0.42)
        last_y = y
    if scale.axis:
        strip = _vertical_text(scale.axis + (", log scale" if scale.log else ""), height)
        sw = min(strip.shape[1], width - 4 - bar_w - 40)
        canvas[:, width - sw:] = strip[:, :sw]
    return canvas


def legend(entries: Sequence[tuple[tuple[int, int, int], str]], width: int, *, scale: float = 0.42,
           background: tuple[int, int, int] = BACKGROUND) -> np.ndarray:
    """A (h, width, 3) legend: one row per (RGB, text) entry, a colour swatch then the text
    (long texts wrap)."""
    import cv2  # noqa: PLC0415 (loaded on use)

    rows: list[tuple[tuple[int, int, int] | None, str]] = []
    room = width - 34
    for color, text in entries:
        line, first = "", True
        for word in text.split():
            trial = f"{line} {word}".strip()
            if cv2.getTextSize(trial, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0] > room and line:
                rows.append((color if first else None, line))
                line, first = word, False
            else:
                line = trial
        rows.append((color if first else None, line))
    step = int(22 * scale / 0.42)
    canvas = np.full((step * len(rows) + 8, width, 3), background, np.uint8)
    for i, (color, text) in enumerate(rows):
        y = 4 + i * step
        if color is not None:
            cv2.rectangle(canvas, (6, y + 3), (22, y + step - 4), tuple(int(c) for c in color), -1)
            cv2.rectangle(canvas, (6, y + 3), (22, y + step - 4), (200, 200, 200), 1)
        _text(canvas, text, 30, y + step - 7, scale)
    return canvas


def caption(text: str, width: int, *, scale: float = 0.55, background: tuple[int, int, int] = BACKGROUND) -> np.ndarray:
    """A (h, width, 3) strip with `text` written on it, wrapped to the width: a picture's title."""
    import cv2  # noqa: PLC0415 (loaded on use)

    lines, line = [], ""
    for word in text.split():
        trial = f"{line} {word}".strip()
        if cv2.getTextSize(trial, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0] > width - 16 and line:
            lines.append(line)
            line = word
        else:
            line = trial
    lines.append(line)
    step = int(24 * scale / 0.5)
    canvas = np.full((step * len(lines) + 10, width, 3), background, np.uint8)
    for i, text_line in enumerate(lines):
        _text(canvas, text_line, 8, 4 + (i + 1) * step - 6, scale)
    return canvas


def stack(images: Sequence[np.ndarray], *, gap: int = 4, gap_color: tuple[int, int, int] = (255, 255, 255),
          background: tuple[int, int, int] = BACKGROUND) -> np.ndarray:
    """Place RGB uint8 images top to bottom (narrower ones padded on the right)."""
    images = [np.asarray(im, np.uint8) for im in images]
    w = max(im.shape[1] for im in images)
    parts = []
    for i, im in enumerate(images):
        if im.shape[1] < w:
            im = np.concatenate([im, np.full((im.shape[0], w - im.shape[1], 3), background, np.uint8)], axis=1)
        if i:
            parts.append(np.broadcast_to(np.array(gap_color, np.uint8), (gap, w, 3)))
        parts.append(im)
    return np.ascontiguousarray(np.concatenate(parts, axis=0))


def busiest_window(a: np.ndarray, b: np.ndarray, mask: np.ndarray, size: int) -> tuple[int, int, int, int]:
    """The size x size pixel window (u0, v0, u1, v1; pixel edges) where two pictures of the
    same view differ most (sum of absolute luminance differences inside `mask`): where the
    wrinkles of one are missing from the other."""
    import cv2  # noqa: PLC0415 (loaded on use)

    diff = np.abs(np.asarray(a, np.float32).mean(axis=2) - np.asarray(b, np.float32).mean(axis=2)) * mask
    h, w = diff.shape
    size = int(min(size, h, w))
    summed = cv2.boxFilter(diff, -1, (size, size), normalize=False, borderType=cv2.BORDER_CONSTANT)
    # Keep windows inside the image: centres at least size/2 from the border.
    half = size // 2
    valid = np.zeros_like(summed, bool)
    valid[half:h - (size - half) + 1, half:w - (size - half) + 1] = True
    r, c = np.unravel_index(np.argmax(np.where(valid, summed, -1)), summed.shape)
    u0, v0 = int(c) - half, int(r) - half
    return (u0 - 0.5, v0 - 0.5, u0 + size - 0.5, v0 + size - 0.5)


def grid_image(rows: Sequence[Sequence[np.ndarray]], col_labels: Sequence[str] | None = None,
               row_labels: Sequence[str] | None = None, gap: int = 4, max_width: int = 3072) -> np.ndarray:
    """Tile RGB uint8 images into one picture, labelled "row / column".

    Images may differ in size (cameras of one rig may): every cell is as large as the
    largest image, each image sits in its cell's top-left corner on white. Wide grids are
    scaled down to at most `max_width` pixels, tile by tile, so the full-size canvas is
    never allocated.
    """
    import cv2  # noqa: PLC0415 (loaded on use)

    h = max(image.shape[0] for row in rows for image in row)
    w = max(image.shape[1] for row in rows for image in row)
    ncol = max(len(r) for r in rows)
    scale = min(1.0, max_width / (ncol * (w + gap) - gap))
    ch, cw, g = max(1, int(h * scale)), max(1, int(w * scale)), max(1, int(round(gap * scale))) if gap else 0
    canvas = np.full((len(rows) * (ch + g) - g, ncol * (cw + g) - g, 3), 255, np.uint8)
    for i, row in enumerate(rows):
        for j, image in enumerate(row):
            text = " / ".join(t for t in ((row_labels[i] if row_labels else ""), (col_labels[j] if col_labels else "")) if t)
            if scale < 1.0:
                size = (max(1, int(image.shape[1] * scale)), max(1, int(image.shape[0] * scale)))
                image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
            tile = label(image, text) if text else image
            th, tw = min(tile.shape[0], ch), min(tile.shape[1], cw)
            canvas[i * (ch + g):i * (ch + g) + th, j * (cw + g):j * (cw + g) + tw] = tile[:th, :tw]
    return canvas


def error_colors(error_m: np.ndarray, scale_m: float) -> np.ndarray:
    """Per-vertex error heatmap (n,) -> (n,3) uint8: blue at 0, red at ≥ scale_m ("jet")."""
    return colormap(error_m, 0.0, scale_m, "jet")


def strain_colors(strain: np.ndarray, scale: float) -> np.ndarray:
    """Signed strain (n,) -> (n,3) uint8: compression blue, 0 white, extension red (±scale saturates)."""
    return colormap(strain, -scale, scale, "bwr")


def texture_colors(uv: np.ndarray, size: int = 1024) -> np.ndarray:
    """The fabric texture's colour at each texture coordinate (n,2) -> (n,3) uint8 (nearest texel)."""

    return fabric_colors(uv, size)


def render_vertex_colors(positions: np.ndarray, faces: np.ndarray, colors: np.ndarray, camera,
                         background: tuple[int, int, int] = (40, 40, 46), *,
                         ctx: GLContext | None = None, body: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Render per-vertex colours, interpolated and shaded by |cos| of the camera-space normal.

    Args:
        positions: (n,3) vertices; faces: (m,3) int triangles.
        colors: (n,3) uint8 (or float 0..255) per-vertex RGB.
        camera: a `mvtex.data.camera.Camera` (zero distortion).
        background: RGB where no triangle is seen.
        ctx: the GL context (`mvtex.render.context.GLContext`); one is made when None.
        body: (positions, faces) of the wearer's body, drawn in `shading.BODY_RGB`.

    Returns:
        (H,W,3) uint8 RGB image.
    """

    if body is not None:
        colors = np.concatenate([np.asarray(colors, np.float64), np.tile(np.asarray(BODY_RGB, np.float64),
                                                                         (len(body[0]), 1))])
        positions, faces, _ = _with_body(positions, faces, body)
    with context_or_new(ctx) as ctx:
        raster = rasterize(ctx, positions, faces, camera)
    normals = vertex_normals(positions, faces, weld_groups(positions)) @ camera.R.T
    shade = 0.35 + 0.65 * np.abs(interpolate(normals, raster, faces)[..., 2:3])
    rgb = interpolate(np.asarray(colors, np.float64), raster, faces) * shade
    img = np.where(raster.mask[..., None], rgb, np.asarray(background, np.float64))
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


ZOOM_RGB = (255, 214, 0)  # the outline of the zoomed window in `comparison_picture`
TRIANGULATED_RGB = (60, 200, 90)
NOT_TRIANGULATED_RGB = (120, 120, 120)


def comparison_scales(faces: np.ndarray, gt: np.ndarray, inferred: np.ndarray, reconstructed: np.ndarray,
                      rest: np.ndarray | None) -> dict[str, ColorScale]:
    """The colour scales of `comparison_picture` (and of the report's 3-D view): "error",
    the distance to gt of the inferred and reconstructed vertices on one logarithmic scale
    (`fit_scale`: top at their 99th percentile, in mm), and "strain", the signed edge strain
    against `rest` of all three meshes on one symmetric linear scale (top at the 99th
    percentile of |strain|)."""

    gt = np.asarray(gt, np.float64)
    errors = [np.linalg.norm(np.asarray(x, np.float64) - gt, axis=1) for x in (inferred, reconstructed)]
    scales = {"error": fit_scale(errors, title="distance to gt", unit="mm", factor=1e3)}
    if rest is not None:
        strain = [np.abs(vertex_strain_energy(np.asarray(x, np.float64), rest, faces)) for x in (gt, inferred, reconstructed)]
        top = fit_scale(strain, log=False).vmax
        scales["strain"] = ColorScale(-top, top, False, "bwr", "edge strain vs rest, - compressed / + stretched", "")
    return scales


def _outline(image: np.ndarray, box: tuple[float, float, float, float], color=ZOOM_RGB) -> np.ndarray:
    import cv2  # noqa: PLC0415 (loaded on use)

    out = np.ascontiguousarray(image.copy())
    u0, v0, u1, v1 = (int(round(b + 0.5)) for b in box)
    cv2.rectangle(out, (u0, v0), (u1 - 1, v1 - 1), color, 2)
    return out


def comparison_picture(camera, faces: np.ndarray, uv: np.ndarray, gt: np.ndarray, inferred: np.ndarray,
                       reconstructed: np.ndarray, rest: np.ndarray | None, *,
                       scales: dict[str, ColorScale] | None = None, triangulated: np.ndarray | None = None,
                       ctx: GLContext | None = None, body: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """gt / inferred / reconstruction side by side from one camera.

    Rows: textured with T_G; the untextured geometry under a key light (`render_shaded`:
    folds show as light and shade); the same zoomed on the window (outlined in the row
    above) where gt's and the inferred mesh's shading differ most; signed strain against
    `rest` (if given); the distance to gt (with `triangulated`, the gt column shows the
    triangulated vertices green instead). Each coloured row ends in its colour bar (axis
    named, with units), and a legend of the other colours closes the picture.

    Args:
        camera: a `mvtex.data.camera.Camera`.
        faces: (m,3) int; uv: (n,2) T_G; gt, inferred, reconstructed: (n,3) positions.
        rest: (n,3) rest shape, or None (no strain row).
        scales: the colour scales (`comparison_scales`, computed when None).
        triangulated: optional (n,) bool.
        ctx: the GL context (`mvtex.render.context.GLContext`); one is made when None.
        body: optional (positions (nb,3), faces (mb,3)) of the wearer, drawn in every panel.

    Returns:
        (H',W',3) uint8 RGB picture.
    """

    scales = comparison_scales(faces, gt, inferred, reconstructed, rest) if scales is None else scales
    meshes = {"gt": gt, "inferred": inferred, "reconstruction": reconstructed}
    h = camera.height
    strip_w = 120
    with context_or_new(ctx) as ctx:
        def shaded(colors_of):
            return [render_vertex_colors(x, faces, colors_of(x), camera, ctx=ctx, body=body) for x in meshes.values()]

        rows: list[tuple[str, list[np.ndarray], np.ndarray]] = []
        blank = np.full((h, strip_w, 3), BACKGROUND, np.uint8)
        rows.append(("texture", [render_textured(ctx, x, faces, uv, camera, body=body) for x in meshes.values()],
                     blank))
        geometry = [render_shaded(ctx, x, faces, camera, body=body) for x in meshes.values()]
        box = garment_box(gt, camera, margin=0.0)
        size = max(32, int(0.4 * max(box[2] - box[0], box[3] - box[1])))

        cloth = rasterize(ctx, np.asarray(gt, np.float64), faces, camera, attributes=False, occluder=body).mask
        window = busiest_window(geometry[0], geometry[1], cloth, size)
        zoom_cam = scaled_camera(camera, window, camera.width, camera.height)
        rows.append(("geometry, key light", [_outline(g, window) for g in geometry], blank))
        rows.append(("geometry, zoom", [render_shaded(ctx, x, faces, zoom_cam, body=body) for x in meshes.values()],
                     blank))
        if rest is not None and "strain" in scales:
            rows.append(("strain", shaded(lambda x: scales["strain"].colors(vertex_strain_energy(x, rest, faces))),
                         colorbar(h, scales["strain"], width=strip_w)))
        err = scales["error"]
        err_row = shaded(lambda x: err.colors(np.linalg.norm(np.asarray(x, np.float64) - gt, axis=1)))
        if triangulated is not None:
            colours = np.where(np.asarray(triangulated)[:, None], np.array([TRIANGULATED_RGB]),
                               np.array([NOT_TRIANGULATED_RGB])).astype(np.uint8)
            err_row[0] = render_vertex_colors(gt, faces, colours, camera, ctx=ctx, body=body)
        rows.append(("distance to gt", err_row, colorbar(h, err, width=strip_w)))
    pictures = []
    for name, panels, strip in rows:
        tiles = [label(p, f"{name} / {col}") for p, col in zip(panels, meshes)]
        pictures.append(side_by_side(tiles + [strip]))
    entries = [(CLOTH_RGB, "cloth, untextured (geometry rows: a key light from the upper left shows the folds)"),
               (BODY_RGB, "the body (mannequin), the same in every panel"),
               (ZOOM_RGB, "outline: the window of the zoom row, where gt's and the inferred mesh's shading differ most"),
               (BACKGROUND, "background")]
    if triangulated is not None:
        entries[2:2] = [(TRIANGULATED_RGB, "gt column, last row: vertices triangulated from the cameras"),
                        (NOT_TRIANGULATED_RGB, "gt column, last row: vertices not triangulated (filled from neighbours)")]
    pictures.append(legend(entries, pictures[0].shape[1], scale=0.5))
    return stack(pictures)
