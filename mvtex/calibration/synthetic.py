"""Synthetic calibration images: the printed board (a textured quad) seen by a camera,
rendered with moderngl through the same projection as every mvtex render, and board poses
that a whole rig sees.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mvtex.calibration.board import BoardSpec, board_image
from mvtex.data.camera import Camera

_QUAD_VERTEX = """
#version 330
uniform mat4 clip_from_cam;
uniform mat4 cam_from_board;
in vec3 in_board;
in vec2 in_texcoord;
out vec2 texcoord;
void main() {
    texcoord = in_texcoord;
    gl_Position = clip_from_cam * (cam_from_board * vec4(in_board, 1.0));
}
"""


_QUAD_FRAGMENT = """
#version 330
uniform sampler2D board;
in vec2 texcoord;
out vec4 color;
void main() {
    color = vec4(vec3(texture(board, texcoord).r), 1.0);
}
"""


class BoardRenderer:
    """Renders the printed board (a textured quad, white margin included) seen by a camera,
    with moderngl.

    `mvtex.render.shading.render_textured` shades meshes with the built-in fabric texture only, so
    the board quad has its own small program here; the projection is the shared
    `mvtex.render.raster.clip_from_camera`, so rendered pixels follow the OpenCV convention.

    It draws in a `mvtex.render.context.GLContext` (given, or its own), made current for each draw
    as the rasterizer does, so it shares a process with other contexts.
    """

    def __init__(self, spec: BoardSpec, pixels_per_square: int = 96, margin_squares: float = 0.5,
                 ctx=None):
        """
        Args:
            spec: the board.
            pixels_per_square: resolution of the board texture (mipmapped).
            margin_squares: white paper around the board, in squares.
            ctx: a `mvtex.render.context.GLContext` (default: a new one, released by `release`).
        """

        from mvtex.render.context import GLContext

        self.spec = spec
        self._owns_gl = ctx is None
        self.gl = GLContext() if ctx is None else ctx
        self.ctx = self.gl.mgl
        self._targets: dict[tuple[int, int], object] = {}
        margin_px = int(round(margin_squares * pixels_per_square))
        image = board_image(spec, pixels_per_square, margin_px)
        # Quad corners in the board frame: the image's outer edges (pixel edges, see board_image).
        margin_m = margin_px / pixels_per_square * spec.square_m
        width_m, height_m = spec.size_m
        x0, y0, x1, y1 = -margin_m, -margin_m, width_m + margin_m, height_m + margin_m
        # GL texture row 0 is the first uploaded row, the image's top (y0): t = 0 at y0.
        quad = np.array([[x0, y0, 0, 0, 0], [x1, y0, 0, 1, 0], [x1, y1, 0, 1, 1],
                         [x0, y0, 0, 0, 0], [x1, y1, 0, 1, 1], [x0, y1, 0, 0, 1]], dtype="f4")
        self._quad_corners = quad[[0, 1, 2, 5], :3].astype(np.float64)
        with self.ctx:
            self._make_objects(image, quad)
        self._maps: dict[tuple, tuple] = {}

    def _make_objects(self, image: np.ndarray, quad: np.ndarray) -> None:
        import moderngl

        self._texture = self.ctx.texture((image.shape[1], image.shape[0]), 1, np.ascontiguousarray(image).tobytes())
        self._texture.build_mipmaps()
        self._texture.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        self._texture.anisotropy = 16.0
        self._texture.repeat_x = self._texture.repeat_y = False
        self._program = self.ctx.program(vertex_shader=_QUAD_VERTEX, fragment_shader=_QUAD_FRAGMENT)
        self._vbo = self.ctx.buffer(quad.tobytes())
        self._vao = self.ctx.vertex_array(self._program, [(self._vbo, "3f 2f", "in_board", "in_texcoord")])

    def render(self, camera: Camera, cam_from_board: np.ndarray, *, background: int = 90,
               supersample: int = 3) -> np.ndarray:
        """The board seen by `camera`, through its lens distortion if it has one.

        Args:
            camera: the camera; only K, `dist` and the size are used.
            cam_from_board: (4,4) or (3,4) float64 rigid transform, board frame -> camera frame.
            background: gray level where the board is not seen.
            supersample: render at this factor and average blocks (anti-aliasing).

        Returns:
            (H,W) uint8 gray image, OpenCV row order. With distortion, a pinhole image of a
            wider field is rendered at the supersampled size and resampled through OpenCV's
            distortion model (`cv2.undistortPoints` of every output pixel, `cv2.remap`).
        """
        import cv2

        pose = np.eye(4)
        pose[:3, :] = np.asarray(cam_from_board, dtype=np.float64)[:3, :]
        s = max(1, int(supersample))
        if np.any(camera.dist != 0):
            pinhole, map_x, map_y = self._distortion_map(camera, s)
            image = cv2.remap(self._draw(pinhole, pose, background), map_x, map_y, cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=background)
        else:
            K = np.diag([s, s, 1.0]) @ camera.K
            K[:2, 2] += (s - 1) / 2.0  # pixel centres of the big image average onto the small one
            image = self._draw(Camera(camera.name, camera.width * s, camera.height * s, K=K, R=np.eye(3),
                                      t=np.zeros(3)), pose, background)
        if s > 1:
            image = cv2.resize(image, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
        return np.ascontiguousarray(image)

    def _distortion_map(self, camera: Camera, s: int):
        """A pinhole camera covering the distorted image's field at s x the resolution, and
        the (H*s, W*s) float32 maps from distorted pixels into it (cached per camera)."""
        import cv2

        key = (camera.width, camera.height, s, camera.K.tobytes(), camera.dist.tobytes())
        if key not in self._maps:
            width, height = camera.width * s, camera.height * s
            v, u = np.mgrid[:height, :width].astype(np.float64)
            small = np.stack([(u - (s - 1) / 2) / s, (v - (s - 1) / 2) / s], axis=-1).reshape(-1, 1, 2)
            criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 20, 1e-10)
            normal = cv2.undistortPoints(small, camera.K, camera.dist, criteria=criteria).reshape(height, width, 2)
            fx, fy, cx, cy = s * camera.K[0, 0], s * camera.K[1, 1], s * camera.K[0, 2], s * camera.K[1, 2]
            px = fx * normal[..., 0] + cx + (s - 1) / 2
            py = fy * normal[..., 1] + cy + (s - 1) / 2
            x0, y0 = np.floor(px.min()) - 2, np.floor(py.min()) - 2
            wide = (int(np.ceil(px.max() - x0)) + 3, int(np.ceil(py.max() - y0)) + 3)
            K = np.array([[fx, 0, cx + (s - 1) / 2 - x0], [0, fy, cy + (s - 1) / 2 - y0], [0, 0, 1.0]])
            pinhole = Camera(camera.name, wide[0], wide[1], K=K, R=np.eye(3), t=np.zeros(3))
            self._maps[key] = (pinhole, (px - x0).astype(np.float32), (py - y0).astype(np.float32))
        return self._maps[key]

    def _draw(self, camera: Camera, pose: np.ndarray, background: int) -> np.ndarray:
        """Draw the quad with a pinhole camera at its size; (H,W) uint8."""


        z = self._quad_corners @ pose[2, :3] + pose[2, 3]
        if z.min() <= 0:
            raise ValueError(f"camera {camera.name!r}: the board is (partly) behind the camera")
        near, far = max(1e-3, 0.5 * float(z.min())), 2.0 * float(z.max()) + 1e-3
        with self.ctx:
            return self._draw_current(camera, pose, background, near, far)

    def _draw_current(self, camera: Camera, pose: np.ndarray, background: int, near: float, far: float) -> np.ndarray:
        import moderngl

        from mvtex.render.raster import clip_from_camera

        self._program["clip_from_cam"].write(clip_from_camera(camera, near, far).T.astype("f4").tobytes())
        self._program["cam_from_board"].write(pose.T.astype("f4").tobytes())
        self._program["board"].value = 0
        size = (camera.width, camera.height)
        if size not in self._targets:  # kept for the renderer's life, one per image size
            self._targets[size] = self.ctx.framebuffer(color_attachments=[self.ctx.texture(size, 1)])
        fbo = self._targets[size]
        fbo.use()
        fbo.clear(background / 255.0, background / 255.0, background / 255.0, 1.0)
        self.ctx.disable(moderngl.CULL_FACE | moderngl.DEPTH_TEST)
        self._texture.use(0)
        self._vao.render(moderngl.TRIANGLES)
        return np.frombuffer(fbo.read(components=1), dtype=np.uint8).reshape(camera.height, camera.width).copy()

    def release(self) -> None:
        """Free this renderer's GL objects, and its context if it made it."""
        if self._owns_gl:
            self.gl.release()  # everything made in it goes with it
            return
        with self.ctx:
            for fbo in self._targets.values():
                for attachment in fbo.color_attachments:
                    attachment.release()
                fbo.release()
            for obj in (self._vao, self._vbo, self._program, self._texture):
                obj.release()
        self._targets.clear()


def random_board_poses(rig, spec: BoardSpec, count: int, *, target=(0.0, 0.0, 0.0), seed: int = 0,
                       max_tilt_deg: float = 35.0, spread_m: float = 0.15, depth_range_m=(-0.25, 0.15),
                       margin_px: float = 8.0, max_tries: int = 10000) -> np.ndarray:
    """Board poses that every camera of a rig sees whole, for synthetic calibrations.

    The board faces the rig (its axes those of the rig's first camera), its centre within
    `spread_m` of `target` sideways and `depth_range_m` along the first camera's axis, and
    tilted up to `max_tilt_deg` about its x and y axes (rolled half that). Poses whose
    outer corners fall within `margin_px` of an image border, or whose back faces a
    camera, are drawn again.

    Returns:
        (count,4,4) float64 world_from_board.
    """
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    first = rig.cameras[0]
    base = first.R.T  # board axes = the first camera's axes, in world coordinates
    w, h = spec.size_m
    outline = np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]], dtype=np.float64)
    poses = []
    for _ in range(max_tries):
        if len(poses) == count:
            break
        tilt = rng.uniform(-1, 1, 3) * np.radians([max_tilt_deg, max_tilt_deg, max_tilt_deg / 2])
        R = base @ Rotation.from_rotvec(tilt).as_matrix()
        centre = np.asarray(target, np.float64) + base @ np.array(
            [rng.uniform(-spread_m, spread_m), rng.uniform(-spread_m, spread_m), rng.uniform(*depth_range_m)])
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = centre - R @ np.array([w / 2, h / 2, 0])
        corners = outline @ T[:3, :3].T + T[:3, 3]
        ok = True
        for cam in rig:
            pixels, z = cam.project(corners)
            facing = np.dot(cam.center - centre, R[:, 2]) < 0
            inside = np.all((pixels > margin_px) & (pixels < np.array([cam.width, cam.height]) - 1 - margin_px))
            if not (facing and np.all(z > 0) and inside):
                ok = False
                break
        if ok:
            poses.append(T)
    if len(poses) < count:
        raise ValueError(f"found only {len(poses)} of {count} board poses every camera sees; move the target")
    return np.stack(poses)


def render_calibration_images(rig, spec: BoardSpec, world_from_board: np.ndarray, out: str | os.PathLike, *,
                              noise: float = 2.0, seed: int = 0, renderer: BoardRenderer | None = None,
                              progress: bool = False) -> Path:
    """Synthetic calibration images: `out/<camera>/frame_NNN.png`, the board at each pose
    seen by each camera, with Gaussian noise of `noise` gray levels.

    Args:
        rig: pinhole cameras.
        world_from_board: (f,4,4) board poses.
        renderer: reuse a BoardRenderer (made here, and released, if None).
    """
    import sys

    from tqdm import tqdm

    from mvtex.util.files import save_png

    out = Path(out)
    rng = np.random.default_rng(seed)
    own = renderer is None
    renderer = BoardRenderer(spec) if own else renderer
    try:
        with tqdm(total=len(rig) * len(world_from_board), desc="render", unit="image", disable=not progress,
                  file=sys.stderr) as bar:
            for cam in rig:
                cam_from_world = np.vstack([cam.cam_from_world, [0, 0, 0, 1]])
                for f, T in enumerate(world_from_board):
                    image = renderer.render(cam, cam_from_world @ T).astype(np.float64)
                    image += rng.normal(0.0, noise, image.shape)
                    save_png(out / cam.name / f"frame_{f:03d}.png", np.clip(np.round(image), 0, 255).astype(np.uint8))
                    bar.update(1)
    finally:
        if own:
            renderer.release()
    return out
