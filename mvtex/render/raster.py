"""Rasterization on moderngl, headless (EGL): triangle ids, perspective-correct
barycentrics and depth per pixel; the same in UV space; two meshes in one pass; textured
shading. This is the only module that talks to OpenGL.

All GL state lives in a `GLContext` that the caller creates once and passes first
(as nvdiffrast's `RasterizeGLContext`): `ctx = GLContext(); rasterize(ctx, ...)`. Nothing
is kept at module level; a worker process creates its own context.

GL's bottom-up rows are undone once, in the projection (`clip_from_camera`): readback row
r, column c is OpenCV pixel (u=c, v=r). Triangle ids are stored +1 in GL (0 = clear) and
the offset is removed here: `tri_id == -1` is background. Images over uv (`rasterize_uv`,
`fabric_texture`) follow DESIGN §3: texel (row r, column c) has centre
((c + 0.5)/W, (r + 0.5)/H), row 0 at v ≈ 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mvtex.data.camera import Camera
from mvtex.render.context import GLContext
from mvtex.util.checks import as_array, as_index, check_instance, check_shape
from mvtex.util.errors import OptionError


def check_mesh(positions, faces, name: str = "positions", dims: int = 3, size: str = "n",
               faces_size: str = "m") -> tuple[np.ndarray, np.ndarray]:
    """Positions (n,dims) finite float64 and faces (m,3) integer indices into them, checked
    before anything reaches GL (OptionError naming the argument)."""

    positions = as_array(positions, name)
    sizes = check_shape(positions, name, (size, dims))
    if not np.all(np.isfinite(positions)):
        raise OptionError(name, "has NaN or infinite values")
    faces = as_array(faces, "faces", None)
    check_shape(faces, "faces", (faces_size, 3))
    if faces.dtype.kind not in "iu":
        raise OptionError("faces", f"must be integers, got {faces.dtype}")
    if faces.size and (faces.min() < 0 or faces.max() >= sizes[size]):
        raise OptionError("faces", f"index vertices outside [0, {sizes[size]})")
    return positions, faces


def _check_draw(ctx, camera=False, occluder=None):

    check_instance(ctx, GLContext, "ctx")
    if camera is not False:
        check_instance(camera, Camera, "camera")
    if occluder is not None:
        if not isinstance(occluder, (tuple, list)) or len(occluder) != 2:
            raise OptionError("occluder", "must be (positions (nb,3), faces (mb,3))")
        return check_mesh(occluder[0], occluder[1], "occluder positions")
    return None


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
    # (u, v, 0) -> clip (2u-1, 2v-1): window row r (read back as row r) has centre v = (r+0.5)/H.
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
        body: (H,W) bool where an occluder (the body) is the nearest surface, when one was
            drawn (`rasterize(..., occluder=...)`); those pixels are background for the mesh
            (tri_id -1, bary and depth 0). None without an occluder.
    """

    tri_id: np.ndarray
    bary: np.ndarray | None
    depth: np.ndarray | None
    body: np.ndarray | None = None

    @property
    def mask(self) -> np.ndarray:
        """(H,W) bool, True where a triangle covers the pixel centre."""
        return self.tri_id >= 0


def _deindexed(points: np.ndarray, faces: np.ndarray) -> bytes:
    corners = points[faces.reshape(-1)].astype(np.float32)
    onehot = np.tile(np.eye(3, dtype=np.float32), (len(faces), 1))
    return np.hstack([corners, onehot]).tobytes()


def _draw_ids(ctx: GLContext, points3: np.ndarray, faces: np.ndarray, width: int, height: int, clip: np.ndarray,
              depth_test: bool, attributes: bool) -> Raster:
    import moderngl  # noqa: PLC0415 (loaded on use)

    if len(faces) == 0:
        empty = np.full((height, width), -1, np.int32)
        return Raster(empty, np.zeros((height, width, 3), np.float32) if attributes else None,
                      np.zeros((height, width), np.float32) if attributes else None)
    gl = ctx.mgl
    with gl:
        prog = ctx._program("raster.vert.glsl", "raster.frag.glsl")
        prog["clip_from_cam"].write(clip.T.astype("f4").tobytes())  # GLSL mat4 is column-major
        vbo = gl.buffer(_deindexed(points3, faces))
        vao = gl.vertex_array(prog, [(vbo, "3f 3f", "in_cam", "in_bary")])
        fbo = ctx._target("ids", width, height)
        fbo.use()
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        gl.disable(moderngl.CULL_FACE)
        if depth_test:
            gl.enable(moderngl.DEPTH_TEST)
        else:
            gl.disable(moderngl.DEPTH_TEST)
        vao.render(moderngl.TRIANGLES)
        ids = np.frombuffer(fbo.read(attachment=0, components=1, dtype="i4"), dtype=np.int32)
        tri_id = ids.reshape(height, width) - 1
        bary = depth = None
        if attributes:
            attrs = np.frombuffer(fbo.read(attachment=1, components=4, dtype="f4"), dtype=np.float32)
            attrs = attrs.reshape(height, width, 4)
            bary = np.ascontiguousarray(attrs[..., :3])
            depth = np.ascontiguousarray(attrs[..., 3])
        vao.release()
        vbo.release()
    return Raster(tri_id=tri_id, bary=bary, depth=depth)


def depth_range(points_cam: np.ndarray) -> tuple[float, float]:
    """Near/far planes that bracket the points in front of the camera."""
    z = points_cam[:, 2]
    z = z[z > 0]
    if z.size == 0:
        return 0.01, 1.0
    return float(max(z.min() * 0.5, 1e-4)), float(z.max() * 2.0)


def rasterize(ctx: GLContext, positions: np.ndarray, faces: np.ndarray, camera: Camera, *,
              attributes: bool = True, occluder: tuple[np.ndarray, np.ndarray] | None = None) -> Raster:
    """Rasterize a mesh from a camera at its resolution.

    Args:
        ctx: the GL context.
        positions: (n,3) world positions (meters).
        faces: (m,3) int vertex indices.
        camera: pinhole camera with zero distortion (else InputError).
        attributes: also read back barycentrics and depth (False: tri_id only, faster).
        occluder: (positions (nb,3), faces (mb,3)) of an opaque surface that is not the mesh
            (the wearer's body): in the depth test with the mesh; where it is nearest the
            mesh is not seen (`Raster.body`).

    Returns:
        Raster with (H,W) fields; pixel centres are sampled (OpenCV convention).
    """
    occluder = _check_draw(ctx, camera, occluder)
    camera.require_renderable()
    positions, faces = check_mesh(positions, faces)
    m = len(faces)
    if occluder is not None:
        body_positions, body_faces = occluder
        positions = np.concatenate([np.asarray(positions, np.float64), np.asarray(body_positions, np.float64)])
        faces = np.concatenate([faces, np.asarray(body_faces) + (len(positions) - len(body_positions))])
    cam = camera.to_camera(positions)
    near, far = depth_range(cam)
    clip = clip_from_camera(camera, near, far)
    raster = _draw_ids(ctx, cam, faces, camera.width, camera.height, clip, True, attributes)
    if occluder is None:
        return raster
    body = raster.tri_id >= m
    tri_id = np.where(body, -1, raster.tri_id).astype(np.int32)
    bary = None if raster.bary is None else np.where(body[..., None], 0, raster.bary).astype(np.float32)
    depth = None if raster.depth is None else np.where(body, 0, raster.depth).astype(np.float32)
    return Raster(tri_id=tri_id, bary=bary, depth=depth, body=body)


def rasterize_uv(ctx: GLContext, uv: np.ndarray, faces: np.ndarray, width: int, height: int, *,
                 attributes: bool = True) -> Raster:
    """Rasterize a mesh in texture space: positions are per-vertex uv in [0,1]².

    Texel (row r, column c) has centre (u, v) = ((c + 0.5)/W, (r + 0.5)/H): row 0 is v ≈ 0
    (DESIGN §3). Only texels whose centre is inside a triangle are written; where
    triangles overlap in uv, the last drawn wins. `depth` is 0.
    """

    _check_draw(ctx)
    uv, faces = check_mesh(uv, faces, "uv", dims=2)
    width, height = as_index(width, "width"), as_index(height, "height")
    if not (1 <= width <= 8192 and 1 <= height <= 8192):
        raise OptionError("width", f"and height must be in 1..8192, got {width}x{height}")
    points = np.hstack([uv, np.zeros((len(uv), 1))])
    return _draw_ids(ctx, points, faces, width, height, _uv_clip(), False, attributes)


class _PairBuffers:
    """Program and buffers of `rasterize_pair` for one face list (made with the context current).

    `faces` are the mesh's m faces followed by the occluder's (offset past the mesh's n
    vertices), `num_vertices` both meshes' vertices."""

    def __init__(self, ctx: GLContext, faces: np.ndarray, num_vertices: int, num_mesh_faces: int, levels: int):
        gl = ctx.mgl
        # The base mesh needs only ids: a program that interpolates nothing draws it faster
        # (same coverage, same ids).
        self.prog_ids = ctx._program("ids.vert.glsl", "ids.frag.glsl")
        self.prog = ctx._program("raster.vert.glsl", "subface.frag.glsl")
        self.n = int(num_vertices)
        self.m = len(faces)
        self.num_mesh_faces = int(num_mesh_faces)
        self.levels = int(levels)
        self.faces = np.asarray(faces, dtype=np.int32)
        self.ibo = gl.buffer(self.faces.tobytes())
        self.vbo = gl.buffer(reserve=self.n * 12)
        self.vao = gl.vertex_array(self.prog_ids, [(self.vbo, "3f", "in_cam")], index_buffer=self.ibo,
                                   index_element_size=4)
        # The subdivided-id mesh de-indexed: each corner carries a one-hot barycentric.
        self.vbo_sub = gl.buffer(reserve=3 * self.m * 12)
        self.bary = gl.buffer(np.tile(np.eye(3, dtype=np.float32), (self.m, 1)).tobytes())
        self.vao_sub = gl.vertex_array(self.prog, [(self.vbo_sub, "3f", "in_cam"), (self.bary, "3f", "in_bary")])

    def release(self) -> None:
        for obj in (self.vao, self.vbo, self.ibo, self.vao_sub, self.vbo_sub, self.bary):
            obj.release()


def _pair_buffers(ctx: GLContext, faces: np.ndarray, num_vertices: int, num_mesh_faces: int,
                  levels: int) -> _PairBuffers:
    # The few cached face lists are compared element by element: cheaper than hashing them.
    for key, pair in ctx._pairs.items():
        if pair.n == num_vertices and pair.levels == levels and pair.num_mesh_faces == num_mesh_faces \
                and pair.faces.shape == np.shape(faces) and np.array_equal(pair.faces, faces):
            ctx._pairs.move_to_end(key)
            return pair
    if len(ctx._pairs) >= 4:
        ctx._pairs.popitem(last=False)[1].release()
    pair = _PairBuffers(ctx, faces, num_vertices, num_mesh_faces, levels)
    ctx._pairs[id(pair)] = pair
    return pair


def body_offsets(num_faces: int, levels: int) -> tuple[int, int]:
    """Where `rasterize_pair` numbers the occluder's faces: (in the base raster, in the
    subdivided raster) — face j of the occluder has id offset + j."""
    return num_faces, 4 ** int(levels) * num_faces


def rasterize_pair(ctx: GLContext, base_positions: np.ndarray, subdivided_positions: np.ndarray,
                   faces: np.ndarray, camera: Camera, *, levels: int = 0, pixels: np.ndarray | None = None,
                   occluder: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Triangle ids of two meshes with the same faces (e.g. gt and inferred) from one camera,
    drawn side by side in one framebuffer: one upload, one readback.

    The second mesh reports ids of its `levels`-times midpoint subdivision
    (`mesh.subdivide` numbering) while only its base faces are drawn: the child face of
    each pixel follows from the pixel's barycentrics in the base face (midpoint subdivision
    does not move the surface, and barycentrics are perspective-correct). That equals
    `rasterize` of the subdivided mesh up to pixel centres exactly on a child edge, at the
    cost of a base raster. Projection and ids are those of `rasterize(..., attributes=False)`.

    Args:
        ctx: the GL context.
        base_positions: (n,3) world positions of the mesh reported with base face ids.
        subdivided_positions: (n,3) world positions of the mesh reported with subdivided ids.
        faces: (m,3) int base faces of both.
        camera: pinhole camera with zero distortion.
        levels: subdivision levels of the second mesh's ids.
        pixels: optional (k,2) projections of every vertex of both meshes: they bound the
            region read back (faster); ids outside it are -1.
        occluder: (positions (nb,3), faces (mb,3)) of an opaque surface drawn with both meshes
            (the body, the same under both): where it is nearest, the raster shows its face
            j as id offset + j (`body_offsets`).

    Returns:
        base_tri_id (H,W) int32 in [0, m), subdivided_tri_id (H,W) int32 in [0, 4^levels m);
        -1 = background; occluder faces at and above `body_offsets(m, levels)`.
    """
    pair = _draw_pair(ctx, base_positions, subdivided_positions, faces, camera, levels, pixels, occluder, False)
    W, H = camera.width, camera.height
    r0, r1, c0, c1 = pair.box
    base_ids = np.full((H, W), -1, np.int32)
    sub_ids = np.full((H, W), -1, np.int32)
    base_ids[r0:r1, c0:c1] = pair.base_tri
    sub_ids[r0:r1, c0:c1] = pair.sub_tri
    return base_ids, sub_ids


@dataclass(frozen=True)
class PairRaster:
    """Both halves of a pair raster with barycentrics (`rasterize_pair_attributes`), in the
    box of the image that holds every id (rows r0:r1, columns c0:c1); -1 elsewhere.

    Attributes:
        box: (r0, r1, c0, c1).
        base_tri, sub_tri: (h,w) int32 ids as `rasterize_pair` gives them (occluder faces
            from `body_offsets(m, levels)` on).
        base_bary, sub_bary: (h,w,3) float32 perspective-correct barycentrics in the base
            face, resp. in the subdivided child face (0 on background and occluder), or
            None (ids only).
    """

    box: tuple[int, int, int, int]
    base_tri: np.ndarray
    sub_tri: np.ndarray
    base_bary: np.ndarray | None
    sub_bary: np.ndarray | None

    def full(self, values: np.ndarray, shape: tuple[int, int], fill=0) -> np.ndarray:
        """An (H,W,...) image of per-box-pixel `values` (h,w,...), `fill` outside the box."""
        r0, r1, c0, c1 = self.box
        out = np.full(tuple(shape) + values.shape[2:], fill, values.dtype)
        out[r0:r1, c0:c1] = values
        return out


def rasterize_pair_attributes(ctx: GLContext, base_positions: np.ndarray, subdivided_positions: np.ndarray,
                              faces: np.ndarray, camera: Camera, *, levels: int = 0, pixels: np.ndarray | None = None,
                              occluder: tuple[np.ndarray, np.ndarray] | None = None) -> PairRaster:
    """`rasterize_pair` that also reads back the barycentrics of both halves (in the base
    face of the first mesh and in the subdivided child face of the second), only in the
    box that holds every id: a `PairRaster`."""
    return _draw_pair(ctx, base_positions, subdivided_positions, faces, camera, levels, pixels, occluder, True)


def _draw_pair(ctx: GLContext, base_positions, subdivided_positions, faces, camera: Camera, levels: int,
               pixels, occluder, attributes: bool) -> PairRaster:
    import moderngl  # noqa: PLC0415 (loaded on use)

    camera.require_renderable()
    base_positions = np.asarray(base_positions, np.float64)
    n, m = len(base_positions), len(faces)
    points = [base_positions, np.asarray(subdivided_positions, np.float64)]
    if occluder is not None:
        points.append(np.asarray(occluder[0], np.float64))
        faces = np.concatenate([np.asarray(faces), np.asarray(occluder[1]) + n])
    cam = camera.to_camera(np.concatenate(points)).astype(np.float32)
    near, far = depth_range(cam)
    W, H = camera.width, camera.height
    base, sub = cam[:n], cam[n:2 * n]
    if occluder is not None:  # the occluder is the same in both halves
        base = np.concatenate([base, cam[2 * n:]])
        sub = np.concatenate([sub, cam[2 * n:]])
    gl = ctx.mgl
    with gl:
        pair = _pair_buffers(ctx, faces, len(base), m, levels)
        clip = clip_from_camera(camera, near, far).T.astype("f4").tobytes()
        pair.prog_ids["clip_from_cam"].write(clip)
        pair.prog["clip_from_cam"].write(clip)
        # A triangle covers only pixel centres inside the box of its projected corners, so
        # the box of all projections (one pixel margin) holds every id: only the box is
        # cleared and read back. With a vertex behind the camera the projection says
        # nothing: the whole image.
        c0, r0, c1, r1 = 0, 0, W, H
        if pixels is not None and len(pixels) and bool(np.all(cam[:2 * n, 2] > 0)):
            # Column by column: NumPy reduces a (k,2) array along axis 0 far slower.
            lo = np.floor([pixels[:, 0].min(), pixels[:, 1].min()]).astype(np.int64) - 1
            hi = np.ceil([pixels[:, 0].max(), pixels[:, 1].max()]).astype(np.int64) + 2
            c0, r0 = int(np.clip(lo[0], 0, W)), int(np.clip(lo[1], 0, H))
            c1, r1 = int(np.clip(hi[0], c0, W)), int(np.clip(hi[1], r0, H))
        w, h = c1 - c0, r1 - r0
        gl.disable(moderngl.CULL_FACE)
        gl.enable(moderngl.DEPTH_TEST)
        if attributes or 2 * W > ctx.max_size:
            # Two framebuffers, each mesh at the image's own window coordinates: the
            # barycentrics are those `rasterize` reads (a viewport shifted by W rounds them
            # differently in float32).
            targets = [ctx._target("ids", W, H, slot) for slot in (0, 1)]
            offsets = (c0, c0)
            for slot, (positions, levels_) in enumerate(((base, 0), (sub, pair.levels))):
                targets[slot].use()
                if w > 0 and h > 0:
                    targets[slot].clear(0.0, 0.0, 0.0, 0.0, depth=1.0, viewport=(c0, r0, w, h))
                gl.viewport = (0, 0, W, H)
                targets[slot].scissor = (c0, r0, w, h)
                pair.vbo_sub.write(positions[pair.faces].tobytes())
                pair.prog["num_faces"].value = pair.num_mesh_faces
                pair.prog["levels"].value = levels_
                pair.prog["body_offset"].value = body_offsets(pair.num_mesh_faces, levels_)[1]
                pair.vao_sub.render(moderngl.TRIANGLES, vertices=3 * pair.m)
                targets[slot].scissor = None
        else:
            fbo = ctx._target("pair", W, H)
            fbo.use()
            if w > 0 and h > 0:
                for x0 in (c0, W + c0):
                    fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0, viewport=(x0, r0, w, h))
            # The viewport clips in clip space: nothing of one mesh can spill into the other
            # half. The scissor box keeps the rasterizer to the box read back (an occluder
            # reaches far past the mesh).
            gl.viewport = (0, 0, W, H)
            fbo.scissor = (c0, r0, w, h)
            pair.vbo.write(base.tobytes())
            pair.vao.render(moderngl.TRIANGLES, vertices=3 * pair.m)
            pair.vbo_sub.write(sub[pair.faces].tobytes())
            gl.viewport = (W, 0, W, H)
            fbo.scissor = (W + c0, r0, w, h)
            pair.prog["num_faces"].value = pair.num_mesh_faces
            pair.prog["levels"].value = pair.levels
            pair.prog["body_offset"].value = body_offsets(pair.num_mesh_faces, pair.levels)[1]
            pair.vao_sub.render(moderngl.TRIANGLES, vertices=3 * pair.m)
            fbo.scissor = None
            targets, offsets = [fbo, fbo], (c0, W + c0)
        halves = []
        for fbo, x0 in zip(targets, offsets):
            if w > 0 and h > 0:
                # GL window row y is image row v (the projection flips once), so no flip here.
                data = fbo.read(attachment=0, components=1, dtype="i4", viewport=(x0, r0, w, h))
                # gl_PrimitiveID restarts at 0 on each draw call; ids are stored +1.
                ids = np.frombuffer(data, np.int32).reshape(h, w) - 1
                bary = None
                if attributes:  # (the two-framebuffer path also serves images too wide for one)
                    data = fbo.read(attachment=1, components=4, dtype="f4", viewport=(x0, r0, w, h))
                    bary = np.frombuffer(data, np.float32).reshape(h, w, 4)[..., :3]
            else:
                ids = np.full((h, w), -1, np.int32)
                bary = np.zeros((h, w, 3), np.float32) if attributes else None
            halves.append((ids, bary))
        gl.viewport = (0, 0, W, H)
    return PairRaster(box=(r0, r1, c0, c1), base_tri=halves[0][0], sub_tri=halves[1][0],
                      base_bary=halves[0][1], sub_bary=halves[1][1])


def interpolate(values: np.ndarray, raster: Raster, faces: np.ndarray) -> np.ndarray:
    """Per-vertex values (n,C) interpolated at every pixel, (H,W,C) float32; 0 on background."""

    check_instance(raster, Raster, "raster")
    values = as_array(values, "values")
    check_shape(values, "values", ("n", "C"))
    faces = as_array(faces, "faces", None)
    check_shape(faces, "faces", ("m", 3))
    if faces.dtype.kind not in "iu" or (faces.size and (faces.min() < 0 or faces.max() >= len(values))):
        raise OptionError("faces", f"must be integer indices into the {len(values)} values")
    if raster.tri_id.size and raster.tri_id.max() >= len(faces):
        raise OptionError("raster", f"names triangle {int(raster.tri_id.max())}, faces has {len(faces)}")
    if raster.bary is None:
        raise OptionError("raster", "has no barycentrics: interpolate needs a raster made with attributes=True")
    mask = raster.mask
    out = np.zeros(raster.tri_id.shape + (values.shape[1],), dtype=np.float32)
    f = np.asarray(faces)[raster.tri_id[mask]]
    b = raster.bary[mask].astype(np.float64)
    out[mask] = np.einsum("kj,kjc->kc", b, values[f].astype(np.float64))
    return out
