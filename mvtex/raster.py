"""Rasterization on moderngl, headless (EGL): triangle ids, perspective-correct
barycentrics and depth per pixel; the same in UV space; textured shading.

One GL context per process, created on first use and reused (`gl_context()`).
GL's bottom-up rows are undone once, in the projection (`clip_from_camera`): readback row
r, column c is OpenCV pixel (u=c, v=r). Triangle ids are stored +1 in GL (0 = clear) and
the offset is removed once, in `rasterize`: `tri_id == -1` is background.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .camera import Camera

_CONTEXT = None


def gl_context():
    """The process-wide moderngl context (EGL, headless); a clear RuntimeError if none."""
    global _CONTEXT
    if _CONTEXT is None:
        import moderngl

        errors = []
        for kwargs in ({"backend": "egl"}, {}):
            try:
                _CONTEXT = moderngl.create_standalone_context(require=330, **kwargs)
                break
            except Exception as err:  # moderngl/glcontext raise plain Exceptions
                errors.append(f"{kwargs or 'default'}: {err}")
        if _CONTEXT is None:
            raise RuntimeError("no OpenGL 3.3 context could be created (needs EGL: on Debian "
                               "libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1, or an NVIDIA driver): "
                               + "; ".join(errors))
    return _CONTEXT


def gl_renderer() -> str:
    """The GL renderer string (e.g. 'llvmpipe (...)' or an NVIDIA GPU)."""
    return str(gl_context().info["GL_RENDERER"])


@lru_cache(maxsize=None)
def _shader_source(name: str) -> str:
    from .resources import resource_path

    return resource_path("shaders", name).read_text()


@lru_cache(maxsize=None)
def _program(name: str):
    ctx = gl_context()
    return ctx.program(vertex_shader=_shader_source(f"{name}.vert.glsl"),
                       fragment_shader=_shader_source(f"{name}.frag.glsl"))


def clip_from_camera(camera: Camera, near: float, far: float) -> np.ndarray:
    """(4,4) float64 matrix from OpenCV camera coordinates to GL clip coordinates.

    Maps pixel (u, v) to GL window (u + 0.5, v + 0.5): with window rows read back bottom-up
    this makes readback row = v and column = u, the OpenCV image, with no flip. It mirrors
    triangle winding, so culling stays off.
    """
    W, H = camera.width, camera.height
    K = camera.K
    return np.array([
        [2 * K[0, 0] / W, 2 * K[0, 1] / W, (2 * K[0, 2] + 1) / W - 1, 0],
        [0, 2 * K[1, 1] / H, (2 * K[1, 2] + 1) / H - 1, 0],
        [0, 0, (far + near) / (far - near), -2 * far * near / (far - near)],
        [0, 0, 1, 0],
    ])


def _uv_clip() -> np.ndarray:
    # (u, v, 0) -> clip (2u-1, 2v-1): texel row r (bottom-up) has centre v = (r+0.5)/H.
    return np.array([[2, 0, 0, -1], [0, 2, 0, -1], [0, 0, 0, 0], [0, 0, 0, 1]], dtype=np.float64)


@dataclass(frozen=True)
class Raster:
    """Per-pixel result of `rasterize` / `rasterize_uv`.

    Attributes:
        tri_id: (H,W) int32 index into `faces` of the visible triangle; -1 on background.
        bary: (H,W,3) float32 perspective-correct barycentrics of the pixel centre in that
            triangle (weights of faces[tri_id, 0..2]); 0 on background. None if not requested.
        depth: (H,W) float32 camera-space z in meters; 0 on background (and in UV space).
            None if not requested.
    """

    tri_id: np.ndarray
    bary: np.ndarray | None
    depth: np.ndarray | None

    @property
    def mask(self) -> np.ndarray:
        """(H,W) bool, True where a triangle covers the pixel centre."""
        return self.tri_id >= 0


class _Target:
    """Framebuffer with an R32I id attachment, an RGBA32F attachment and a depth buffer."""

    def __init__(self, width: int, height: int):
        ctx = gl_context()
        self.size = (width, height)
        self.ids = ctx.texture(self.size, 1, dtype="i4")
        self.attrs = ctx.texture(self.size, 4, dtype="f4")
        self.depth = ctx.depth_renderbuffer(self.size)
        self.fbo = ctx.framebuffer(color_attachments=[self.ids, self.attrs], depth_attachment=self.depth)


@lru_cache(maxsize=8)
def _target(width: int, height: int) -> _Target:
    return _Target(width, height)


def _deindexed(points: np.ndarray, faces: np.ndarray) -> bytes:
    corners = points[faces.reshape(-1)].astype(np.float32)
    onehot = np.tile(np.eye(3, dtype=np.float32), (len(faces), 1))
    return np.hstack([corners, onehot]).tobytes()


def _draw_ids(points3: np.ndarray, faces: np.ndarray, width: int, height: int, clip: np.ndarray,
              depth_test: bool, attributes: bool) -> Raster:
    import moderngl

    if len(faces) == 0:
        empty = np.full((height, width), -1, np.int32)
        return Raster(empty, np.zeros((height, width, 3), np.float32) if attributes else None,
                      np.zeros((height, width), np.float32) if attributes else None)
    ctx = gl_context()
    prog = _program("raster")
    prog["clip_from_cam"].write(clip.T.astype("f4").tobytes())  # GLSL mat4 is column-major
    vbo = ctx.buffer(_deindexed(points3, faces))
    vao = ctx.vertex_array(prog, [(vbo, "3f 3f", "in_cam", "in_bary")])
    target = _target(width, height)
    target.fbo.use()
    target.fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
    ctx.disable(moderngl.CULL_FACE)
    if depth_test:
        ctx.enable(moderngl.DEPTH_TEST)
    else:
        ctx.disable(moderngl.DEPTH_TEST)
    vao.render(moderngl.TRIANGLES)
    ids = np.frombuffer(target.fbo.read(attachment=0, components=1, dtype="i4"), dtype=np.int32)
    tri_id = ids.reshape(height, width) - 1
    bary = depth = None
    if attributes:
        attrs = np.frombuffer(target.fbo.read(attachment=1, components=4, dtype="f4"), dtype=np.float32)
        attrs = attrs.reshape(height, width, 4)
        bary = np.ascontiguousarray(attrs[..., :3])
        depth = np.ascontiguousarray(attrs[..., 3])
    vao.release()
    vbo.release()
    return Raster(tri_id=tri_id, bary=bary, depth=depth)


def _check_renderable(camera: Camera) -> None:
    if np.any(camera.dist != 0):
        raise ValueError(f"camera {camera.name!r} has non-zero distortion {camera.dist.tolist()}: "
                         "rendering needs undistorted (pinhole) cameras; undistort the images first")


def depth_range(points_cam: np.ndarray) -> tuple[float, float]:
    """Near/far planes that bracket the points in front of the camera."""
    z = points_cam[:, 2]
    z = z[z > 0]
    if z.size == 0:
        return 0.01, 1.0
    return float(max(z.min() * 0.5, 1e-4)), float(z.max() * 2.0)


def rasterize(positions: np.ndarray, faces: np.ndarray, camera: Camera, *, attributes: bool = True) -> Raster:
    """Rasterize a mesh from a camera at its resolution.

    Args:
        positions: (n,3) world positions (meters).
        faces: (m,3) int vertex indices.
        camera: pinhole camera with zero distortion.
        attributes: also read back barycentrics and depth (False: tri_id only, faster).

    Returns:
        Raster with (H,W) fields; pixel centres are sampled (OpenCV convention).
    """
    _check_renderable(camera)
    cam = camera.to_camera(positions)
    near, far = depth_range(cam)
    clip = clip_from_camera(camera, near, far)
    return _draw_ids(cam, np.asarray(faces), camera.width, camera.height, clip, True, attributes)


def rasterize_uv(uv: np.ndarray, faces: np.ndarray, width: int, height: int, *, attributes: bool = True) -> Raster:
    """Rasterize a mesh in texture space: positions are per-vertex uv in [0,1]².

    Texel (row r, column c) has centre (u, v) = ((c + 0.5)/W, (r + 0.5)/H): row 0 is v ≈ 0
    (GL texture order). Only texels whose centre is inside a triangle are written; where
    triangles overlap in uv, the last drawn wins. `depth` is 0.
    """
    uv = np.asarray(uv, dtype=np.float64)
    points = np.hstack([uv, np.zeros((len(uv), 1))])
    return _draw_ids(points, np.asarray(faces), width, height, _uv_clip(), False, attributes)


def interpolate(values: np.ndarray, raster: Raster, faces: np.ndarray) -> np.ndarray:
    """Per-vertex values (n,C) interpolated at every pixel, (H,W,C) float32; 0 on background."""
    values = np.asarray(values)
    if raster.bary is None:
        raise ValueError("interpolate needs a raster with barycentrics (attributes=True)")
    mask = raster.mask
    out = np.zeros(raster.tri_id.shape + (values.shape[1],), dtype=np.float32)
    f = np.asarray(faces)[raster.tri_id[mask]]
    b = raster.bary[mask].astype(np.float64)
    out[mask] = np.einsum("kj,kjc->kc", b, values[f].astype(np.float64))
    return out


# -- textured shading ---------------------------------------------------------------------

@lru_cache(maxsize=4)
def fabric_texture(size: int = 1024, seed: int = 7) -> np.ndarray:
    """A fabric-like RGB texture (size,size,3) uint8, row 0 at v = 1 (picture order).

    A printed plaid with fine threads (period 1/128 of the atlas), a coarser check and
    small dots: dense enough that sliding by a fraction of a centimetre shows.
    """
    rng = np.random.default_rng(seed)
    t = (np.arange(size) + 0.5) / size
    u, v = np.meshgrid(t, t[::-1])
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


@lru_cache(maxsize=4)
def _color_target(width: int, height: int):
    # Kept alive (cached) rather than released: releasing the bound framebuffer leaves GL
    # with no valid draw target for the next call.
    ctx = gl_context()
    return ctx.framebuffer(color_attachments=[ctx.texture((width, height), 4)],
                           depth_attachment=ctx.depth_renderbuffer((width, height)))


@lru_cache(maxsize=2)
def _fabric_gl(size: int):
    import moderngl

    ctx = gl_context()
    image = fabric_texture(size)[::-1]  # GL row 0 is v = 0
    tex = ctx.texture((size, size), 3, np.ascontiguousarray(image).tobytes())
    tex.build_mipmaps()
    tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
    tex.anisotropy = 8.0
    tex.repeat_x = tex.repeat_y = True
    return tex


def render_textured(positions: np.ndarray, faces: np.ndarray, texcoords: np.ndarray, camera: Camera, *,
                    normals: np.ndarray | None = None, background: tuple[int, int, int] = (40, 40, 46),
                    supersample: int = 2, texture_size: int = 1024) -> np.ndarray:
    """Shade a mesh with the fabric texture at any per-vertex texcoords.

    Args:
        positions: (n,3) world positions. faces: (m,3). texcoords: (n,2) per-vertex uv.
        normals: (n,3) vertex normals (computed with seam copies welded if None).
        supersample: render at this factor and downsample (anti-aliasing).

    Returns:
        (H,W,3) uint8 RGB image, OpenCV row order.
    """
    import cv2
    import moderngl

    from .mesh import vertex_normals, weld_groups

    _check_renderable(camera)
    positions = np.asarray(positions, dtype=np.float64)
    if normals is None:
        normals = vertex_normals(positions, faces, weld_groups(positions))
    cam = camera.to_camera(positions)
    near, far = depth_range(cam)
    s = max(1, int(supersample))
    big = Camera(camera.name, camera.width * s, camera.height * s,
                 K=np.diag([s, s, 1.0]) @ camera.K + np.array([[0, 0, (s - 1) / 2], [0, 0, (s - 1) / 2], [0, 0, 0]]),
                 R=camera.R, t=camera.t)
    clip = clip_from_camera(big, near, far)
    ctx = gl_context()
    prog = _program("textured")
    prog["clip_from_cam"].write(clip.T.astype("f4").tobytes())
    prog["fabric"].value = 0
    data = np.hstack([cam, normals @ camera.R.T, np.asarray(texcoords, dtype=np.float64)]).astype("f4")
    vbo = ctx.buffer(data.tobytes())
    ibo = ctx.buffer(np.asarray(faces, dtype=np.int32).tobytes())
    vao = ctx.vertex_array(prog, [(vbo, "3f 3f 2f", "in_cam", "in_normal", "in_texcoord")], index_buffer=ibo,
                           index_element_size=4)
    fbo = _color_target(big.width, big.height)
    fbo.use()
    bg = np.asarray(background, dtype=np.float64) / 255
    fbo.clear(*bg, 1.0, depth=1.0)
    ctx.disable(moderngl.CULL_FACE)
    ctx.enable(moderngl.DEPTH_TEST)
    _fabric_gl(texture_size).use(0)
    vao.render(moderngl.TRIANGLES)
    img = np.frombuffer(fbo.read(components=3), dtype=np.uint8).reshape(big.height, big.width, 3)
    for obj in (vao, vbo, ibo):
        obj.release()
    if s > 1:
        img = cv2.resize(img, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(img)
