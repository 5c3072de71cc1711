"""Pictures for people: colormaps, per-pixel heatmaps and per-vertex error / strain /
texture colours, shaded renders of vertex colours, the gt / inferred / reconstruction
comparison, labelled side-by-side panels and grids.

The one "jet" map (blue = 0, red ≥ vmax) is `colormap(..., "jet")`; heatmaps and error
colours both use it. GL renders go through `mvtex.render.raster`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np

if TYPE_CHECKING:
    from mvtex.render.context import GLContext


BACKGROUND = (24, 24, 28)


def colormap(values: np.ndarray, vmin: float, vmax: float, name: str = "jet") -> np.ndarray:
    """Values (...) -> colours (..., 3) uint8 of a matplotlib colormap over [vmin, vmax] (clipped)."""
    from matplotlib import colormaps

    x = np.clip((np.asarray(values, np.float64) - vmin) / (vmax - vmin), 0.0, 1.0)
    return (colormaps[name](x)[..., :3] * 255.0 + 0.5).astype(np.uint8)


def heatmap(error: np.ndarray, vmax: float = 0.04, *, background: tuple[int, int, int] = BACKGROUND) -> np.ndarray:
    """Colour a per-pixel error image with matplotlib's "jet" map.

    Args:
        error: (H,W) float; NaN where undefined (drawn as `background`).
        vmax: error drawn fully red (and everything above it); 0 is blue.

    Returns:
        (H,W,3) uint8 RGB.
    """
    e = np.asarray(error, dtype=np.float64)
    valid = np.isfinite(e)
    rgb = colormap(np.where(valid, e, 0.0), 0.0, float(vmax), "jet")
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
    """Tile RGB uint8 images into one picture, labelled "row / column".

    Images may differ in size (cameras of one rig may): every cell is as large as the
    largest image, each image sits in its cell's top-left corner on white. Wide grids are
    scaled down to at most `max_width` pixels, tile by tile, so the full-size canvas is
    never allocated.
    """
    import cv2

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
    from mvtex.render.shading import fabric_colors

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
    from mvtex.data.mesh import vertex_normals, weld_groups
    from mvtex.render.context import context_or_new
    from mvtex.render.raster import interpolate, rasterize
    from mvtex.render.shading import BODY_RGB, _with_body

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


def comparison_picture(camera, faces: np.ndarray, uv: np.ndarray, gt: np.ndarray, inferred: np.ndarray,
                       reconstructed: np.ndarray, rest: np.ndarray | None, *, error_scale_m: float = 0.01,
                       strain_scale: float = 0.1, triangulated: np.ndarray | None = None,
                       ctx: GLContext | None = None, body: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """gt / inferred / reconstruction side by side from one camera.

    Rows: textured with T_G; signed strain against `rest` (if given); the error ‖x - gt‖
    heatmap (with `triangulated`, the gt column shows triangulated vertices green instead).

    Args:
        camera: a `mvtex.data.camera.Camera`.
        faces: (m,3) int; uv: (n,2) T_G; gt, inferred, reconstructed: (n,3) positions.
        rest: (n,3) rest shape, or None (no strain row).
        error_scale_m: error heatmaps run from blue (0) to red (≥ this).
        strain_scale: strain runs from blue (-this) to red (+this).
        triangulated: optional (n,) bool.
        ctx: the GL context (`mvtex.render.context.GLContext`); one is made when None.
        body: optional (positions (nb,3), faces (mb,3)) of the wearer, drawn in every panel.

    Returns:
        (H',W',3) uint8 RGB picture.
    """
    from mvtex.data.mesh import vertex_strain_energy
    from mvtex.render.context import GLContext
    from mvtex.render.shading import render_textured

    if ctx is None:
        with GLContext() as own:
            return comparison_picture(camera, faces, uv, gt, inferred, reconstructed, rest, error_scale_m=error_scale_m,
                                      strain_scale=strain_scale, triangulated=triangulated, ctx=own, body=body)
    meshes = {"gt": gt, "inferred": inferred, "reconstruction": reconstructed}

    def shaded(colors_of):
        return [render_vertex_colors(x, faces, colors_of(x), camera, ctx=ctx, body=body) for x in meshes.values()]

    rows = [[render_textured(ctx, x, faces, uv, camera, body=body) for x in meshes.values()]]
    labels = ["texture"]
    if rest is not None:
        rows.append(shaded(lambda x: strain_colors(vertex_strain_energy(x, rest, faces), strain_scale)))
        labels.append(f"strain +-{strain_scale:g}")
    err_row = shaded(lambda x: error_colors(np.linalg.norm(x - gt, axis=1), error_scale_m))
    if triangulated is not None:
        grey = np.where(triangulated[:, None], np.array([[60, 200, 90]]), np.array([[120, 120, 120]])).astype(np.uint8)
        err_row[0] = render_vertex_colors(gt, faces, grey, camera, ctx=ctx, body=body)
    rows.append(err_row)
    labels.append(f"error 0-{error_scale_m * 1e3:g}mm" + ("" if triangulated is None else " (gt: green = triangulated)"))
    return grid_image(rows, col_labels=list(meshes), row_labels=labels)
