"""Shaded pictures of meshes: the built-in fabric texture and textured renders
(`render_textured`), drawn through the same projection as the rasterizer.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from mvtex.data.camera import MAX_IMAGE_SIZE, Camera
from mvtex.data.mesh import face_normals, vertex_normals, weld_groups
from mvtex.render.context import GLContext
from mvtex.render.raster import _check_draw, check_mesh, clip_from_camera, depth_range
from mvtex.util.checks import as_array, check_shape


@lru_cache(maxsize=4)
def fabric_texture(size: int = 1024, seed: int = 7) -> np.ndarray:
    """A fabric-like RGB texture (size,size,3) uint8 over uv; row 0 at v ≈ 0 (DESIGN §3:
    texel (r, c) has centre ((c + 0.5)/size, (r + 0.5)/size); flip rows to show v up).

    A printed plaid with fine threads (period 1/128 of the atlas), a coarser check and
    small dots: dense enough that sliding by a fraction of a centimeter shows.
    """
    rng = np.random.default_rng(seed)
    t = (np.arange(size) + 0.5) / size
    u, v = np.meshgrid(t, t)
    base = np.array([0.82, 0.78, 0.70])
    img = np.ones((size, size, 3)) * base
    # Coarse check in two colours.
    check = ((np.floor(u * 16) + np.floor(v * 16)) % 2)[..., None]
    img = img * (1 - 0.18 * check) + 0.18 * check * np.array([0.35, 0.45, 0.75])
    # Plaid bands.
    for period, width, color, strength in ((1 / 8, 0.012, (0.75, 0.2, 0.2), 0.7), (1 / 32, 0.002, (0.15, 0.25, 0.15), 0.5)):
        for coord in (u, v):
            d = np.abs((coord + period / 2) % period - period / 2)
            band = np.clip(1 - d / width, 0, 1)[..., None]
            img = img * (1 - strength * band) + strength * band * np.array(color)
    # Fine threads.
    threads = 0.5 + 0.5 * np.cos(2 * np.pi * u * 128) * np.cos(2 * np.pi * v * 128)
    img *= (0.88 + 0.12 * threads)[..., None]
    # Small dots on a jittered grid, each a little different in colour.
    grid = 64
    cu, cv = np.floor(u * grid), np.floor(v * grid)
    jitter = rng.uniform(0.3, 0.7, size=(grid, grid, 2))
    du = u * grid - cu - jitter[cv.astype(int), cu.astype(int), 0]
    dv = v * grid - cv - jitter[cv.astype(int), cu.astype(int), 1]
    dot = (du ** 2 + dv ** 2 < 0.12 ** 2)[..., None]
    hue = rng.uniform(0, 1, size=(grid, grid, 3))[cv.astype(int), cu.astype(int)]
    img = np.where(dot, 0.15 + 0.5 * hue, img)
    return np.clip(img * 255, 0, 255).astype(np.uint8)


def fabric_colors(uv: np.ndarray, size: int = 1024) -> np.ndarray:
    """The fabric texture's colour at texture coordinates (n,2) -> (n,3) uint8 (nearest texel)."""
    tex = fabric_texture(size)
    uv = np.asarray(uv, np.float64)
    col = np.clip(np.floor(uv[:, 0] * size), 0, size - 1).astype(np.int64)
    row = np.clip(np.floor(uv[:, 1] * size), 0, size - 1).astype(np.int64)
    return tex[row, col]


def _fabric_gl(ctx: GLContext, size: int):
    import moderngl  # noqa: PLC0415 (loaded on use)

    if size not in ctx._fabric:
        # GL texture row 0 is v = 0: the same order as `fabric_texture`, uploaded as is.
        tex = ctx.mgl.texture((size, size), 3, np.ascontiguousarray(fabric_texture(size)).tobytes())
        tex.build_mipmaps()
        tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        tex.anisotropy = 8.0
        tex.repeat_x = tex.repeat_y = True
        ctx._fabric[size] = tex
    return ctx._fabric[size]


BODY_RGB = (168, 163, 156)  # the body's neutral matte material (a mannequin's grey)


def _with_body(positions: np.ndarray, faces: np.ndarray, body: tuple[np.ndarray, np.ndarray] | None):
    """Mesh and body as one mesh (the body's faces after the mesh's), and (n_all,) float32
    1 on the body's vertices."""
    positions = np.asarray(positions, np.float64)
    faces = np.asarray(faces, np.int64)
    if body is None:
        return positions, faces, np.zeros(len(positions), np.float32)
    body_positions, body_faces = np.asarray(body[0], np.float64), np.asarray(body[1], np.int64)
    matte = np.r_[np.zeros(len(positions), np.float32), np.ones(len(body_positions), np.float32)]
    return np.concatenate([positions, body_positions]), np.concatenate([faces, body_faces + len(positions)]), matte


def _draw(ctx: GLContext, vao, big: Camera, background: tuple[int, int, int], bind=None) -> np.ndarray:
    """Draw `vao` (inside the caller's `with ctx.mgl`) into a colour target of `big`'s size
    over `background`, depth-tested with culling off (the projection mirrors winding), after
    `bind()`; the (H,W,3) uint8 RGB readback, OpenCV row order."""
    import moderngl  # noqa: PLC0415 (loaded on use)

    fbo = ctx._target("color", big.width, big.height)
    fbo.use()
    fbo.clear(*(np.asarray(background, np.float64) / 255), 1.0, depth=1.0)
    ctx.mgl.disable(moderngl.CULL_FACE)
    ctx.mgl.enable(moderngl.DEPTH_TEST)
    if bind is not None:
        bind()
    vao.render(moderngl.TRIANGLES)
    return np.frombuffer(fbo.read(components=3), dtype=np.uint8).reshape(big.height, big.width, 3)


def _downsampled(img: np.ndarray, camera: Camera, s: int) -> np.ndarray:
    """A render supersampled by `s` brought back to `camera`'s size (area average)."""
    import cv2  # noqa: PLC0415 (loaded on use)

    if s > 1:
        img = cv2.resize(img, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(img)


def render_textured(ctx: GLContext, positions: np.ndarray, faces: np.ndarray, texcoords: np.ndarray,
                    camera: Camera, *, normals: np.ndarray | None = None,
                    background: tuple[int, int, int] = (40, 40, 46), supersample: int = 2,
                    texture_size: int = 1024, body: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Shade a mesh with the fabric texture at any per-vertex texcoords.

    Args:
        ctx: the GL context.
        positions: (n,3) world positions. faces: (m,3). texcoords: (n,2) per-vertex uv.
        camera: pinhole camera with zero distortion.
        normals: (n,3) vertex normals (computed with seam copies welded if None).
        supersample: render at this factor and downsample (anti-aliasing).
        body: (positions (nb,3), faces (mb,3)) of the wearer's body, drawn with the mesh in a
            neutral matte material (`BODY_RGB`) under the same light.

    Returns:
        (H,W,3) uint8 RGB image, OpenCV row order.
    """

    body = _check_draw(ctx, camera, body)
    camera.require_renderable()
    positions, faces = check_mesh(positions, faces)
    texcoords = as_array(texcoords, "texcoords")
    check_shape(texcoords, "texcoords", (len(positions), 2))
    if normals is not None:
        normals = as_array(normals, "normals")
        check_shape(normals, "normals", (len(positions), 3))
    if normals is None:
        normals = vertex_normals(positions, faces, weld_groups(positions))
    if body is not None:
        body_normals = vertex_normals(np.asarray(body[0], np.float64), body[1], weld_groups(body[0]))
        normals = np.concatenate([normals, body_normals])
        texcoords = np.concatenate([np.asarray(texcoords, np.float64), np.zeros((len(body[0]), 2))])
    positions, faces, matte = _with_body(positions, faces, body)
    cam = camera.to_camera(positions)
    near, far = depth_range(cam)
    # Supersampled, as far as the GL's and the camera model's largest image allow.
    s = max(1, min(int(supersample), min(ctx.max_size, MAX_IMAGE_SIZE) // max(camera.width, camera.height)))
    big = Camera(camera.name, camera.width * s, camera.height * s,
                 K=np.diag([s, s, 1.0]) @ camera.K + np.array([[0, 0, (s - 1) / 2], [0, 0, (s - 1) / 2], [0, 0, 0]]),
                 R=camera.R, t=camera.t)
    clip = clip_from_camera(big, near, far)
    data = np.hstack([cam, normals @ camera.R.T, np.asarray(texcoords, dtype=np.float64), matte[:, None]]).astype("f4")
    gl = ctx.mgl
    with gl:
        prog = ctx._program("textured.vert.glsl", "textured.frag.glsl")
        prog["clip_from_cam"].write(clip.T.astype("f4").tobytes())
        prog["fabric"].value = 0
        prog["matte_color"].value = tuple(c / 255 for c in BODY_RGB)
        vbo = gl.buffer(data.tobytes())
        ibo = gl.buffer(np.asarray(faces, dtype=np.int32).tobytes())
        vao = gl.vertex_array(prog, [(vbo, "3f 3f 2f 1f", "in_cam", "in_normal", "in_texcoord", "in_matte")],
                              index_buffer=ibo, index_element_size=4)
        img = _draw(ctx, vao, big, background, bind=lambda: _fabric_gl(ctx, texture_size).use(0))
        for obj in (vao, vbo, ibo):
            obj.release()
    return _downsampled(img, camera, s)


CLOTH_RGB = (150, 178, 214)  # the cloth's colour in untextured (`render_shaded`) pictures

# Key light of `render_shaded`, in camera coordinates (x right, y down, z forward): from the
# upper left, about 50 degrees off the viewing direction, so that folds cast light and shade.
KEY_LIGHT = (-0.55, -0.6, -0.58)
SHADED_AMBIENT = 0.18
SHADED_DIFFUSE = 0.82


def key_light() -> np.ndarray:
    """(3,) unit vector toward `render_shaded`'s key light, in camera coordinates."""
    light = np.asarray(KEY_LIGHT, np.float64)
    return light / np.linalg.norm(light)


def scaled_camera(camera: Camera, box: tuple[float, float, float, float], width: int, height: int) -> Camera:
    """The camera whose image is the pixel box (u0, v0, u1, v1) of `camera` (pixel edges,
    OpenCV pixel centres at integers: the full image is (-0.5, -0.5, W-0.5, H-0.5)),
    resampled to width x height: a zoom rendered at full resolution instead of an
    enlarged crop."""
    u0, v0, u1, v1 = (float(b) for b in box)
    if not (u1 > u0 and v1 > v0):
        raise ValueError(f"empty box {box}")
    sx, sy = width / (u1 - u0), height / (v1 - v0)
    K = np.asarray(camera.K, np.float64)
    # New pixel centre u' satisfies u' + 0.5 = sx (u - u0), for u the old pixel coordinate.
    K2 = np.array([[K[0, 0] * sx, K[0, 1] * sx, (K[0, 2] - u0) * sx - 0.5],
                   [0.0, K[1, 1] * sy, (K[1, 2] - v0) * sy - 0.5],
                   [0.0, 0.0, 1.0]])
    return Camera(camera.name, int(width), int(height), K=K2, R=camera.R, t=camera.t)


def _supersampled(camera: Camera, s: int) -> Camera:
    return scaled_camera(camera, (-0.5, -0.5, camera.width - 0.5, camera.height - 0.5), camera.width * s,
                         camera.height * s)


def render_shaded(ctx: GLContext, positions: np.ndarray, faces: np.ndarray, camera: Camera, *,
                  normals: str | np.ndarray = "vertex", body: tuple[np.ndarray, np.ndarray] | None = None,
                  cloth_rgb: tuple[int, int, int] = CLOTH_RGB, background: tuple[int, int, int] = (40, 40, 46),
                  supersample: int = 2) -> np.ndarray:
    """The mesh's geometry, untextured, lit by a key light at an angle: folds and wrinkles
    show as light and shade, whatever the texture does.

    Each pixel is ``albedo * (SHADED_AMBIENT + SHADED_DIFFUSE * max(0, n . l))`` with ``l``
    `key_light()` and ``n`` the surface normal in camera coordinates, turned toward the
    camera (both sides lit); albedo is `cloth_rgb` on the mesh and `BODY_RGB` on the body.

    Args:
        ctx: the GL context.
        positions: (n,3) world positions. faces: (m,3).
        camera: pinhole camera with zero distortion.
        normals: "vertex" (smooth: area-weighted vertex normals, seam copies welded),
            "face" (flat: each triangle's own normal), or an (n,3) array of vertex normals.
        body: (positions (nb,3), faces (mb,3)) of the wearer, drawn in `BODY_RGB` (smooth).
        supersample: render at this factor and downsample (anti-aliasing).

    Returns:
        (H,W,3) uint8 RGB image, OpenCV row order.
    """

    camera.require_pinhole()
    positions = np.asarray(positions, np.float64)
    faces = np.asarray(faces, np.int64)
    if isinstance(normals, str) and normals == "face":
        # One normal per corner: de-index the mesh (three vertices per face).
        fn = face_normals(positions, faces)
        positions, normals_v = positions[faces.reshape(-1)], np.repeat(fn, 3, axis=0)
        faces = np.arange(len(positions), dtype=np.int64).reshape(-1, 3)
    elif isinstance(normals, str) and normals == "vertex":
        normals_v = vertex_normals(positions, faces, weld_groups(positions))
    elif isinstance(normals, str):
        raise ValueError(f"normals must be 'vertex', 'face' or an (n,3) array, got {normals!r}")
    else:
        normals_v = np.asarray(normals, np.float64)
        if normals_v.shape != positions.shape:
            raise ValueError(f"normals must have the positions' shape {positions.shape}, got {normals_v.shape}")
    if body is not None:
        body_positions = np.asarray(body[0], np.float64)
        normals_v = np.concatenate([normals_v, vertex_normals(body_positions, body[1], weld_groups(body_positions))])
    positions, faces, matte = _with_body(positions, faces, body)
    cam = camera.to_camera(positions)
    near, far = depth_range(cam)
    s = max(1, min(int(supersample), min(ctx.max_size, MAX_IMAGE_SIZE) // max(camera.width, camera.height)))
    big = _supersampled(camera, s)
    clip = clip_from_camera(big, near, far)
    data = np.hstack([cam, normals_v @ camera.R.T, matte[:, None]]).astype("f4")
    gl = ctx.mgl
    with gl:
        prog = ctx._program("shaded.vert.glsl", "shaded.frag.glsl")
        prog["clip_from_cam"].write(clip.T.astype("f4").tobytes())
        prog["light_dir"].value = tuple(float(x) for x in key_light())
        prog["ambient"].value = SHADED_AMBIENT
        prog["diffuse"].value = SHADED_DIFFUSE
        prog["cloth_color"].value = tuple(c / 255 for c in cloth_rgb)
        prog["matte_color"].value = tuple(c / 255 for c in BODY_RGB)
        vbo = gl.buffer(data.tobytes())
        ibo = gl.buffer(np.asarray(faces, dtype=np.int32).tobytes())
        vao = gl.vertex_array(prog, [(vbo, "3f 3f 1f", "in_cam", "in_normal", "in_matte")],
                              index_buffer=ibo, index_element_size=4)
        img = _draw(ctx, vao, big, background)
        for obj in (vao, vbo, ibo):
            obj.release()
    return _downsampled(img, camera, s)


def garment_box(positions: np.ndarray, camera: Camera, *, margin: float = 0.06,
                aspect: float | None = 1.0) -> tuple[float, float, float, float]:
    """The pixel box (u0, v0, u1, v1) around a mesh's projection (vertices in front of the
    camera), widened by `margin` of its size on each side and, with `aspect` (width /
    height), grown to that aspect around its centre. Pixel edges, as `scaled_camera`."""
    uv, depth = camera.project(np.asarray(positions, np.float64))
    uv = uv[depth > 0]
    if len(uv) == 0:
        return (-0.5, -0.5, camera.width - 0.5, camera.height - 0.5)
    lo, hi = uv.min(axis=0) - 0.5, uv.max(axis=0) + 0.5
    size = hi - lo
    lo, hi = lo - margin * size, hi + margin * size
    if aspect is not None:
        centre, size = (lo + hi) / 2, hi - lo
        w = max(size[0], size[1] * aspect)
        h = w / aspect
        lo, hi = centre - (w / 2, h / 2), centre + (w / 2, h / 2)
    return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
