"""Synthetic calibration images: the printed board (a textured quad, drawn by
`mvtex.render.quad`) seen by a camera through its lens, and board poses that a whole rig sees.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from mvtex.calibration.board import BoardSpec, board_image
from mvtex.data.camera import Camera
from mvtex.render.context import GLContext
from mvtex.render.quad import QuadRenderer
from mvtex.util.files import save_png


class BoardRenderer:
    """Renders the printed board (a textured quad, white margin included) seen by a camera,
    through its lens distortion if it has one.

    The quad is drawn by `mvtex.render.quad.QuadRenderer` (the shared projection, so pixels
    follow the OpenCV convention) in a `mvtex.render.context.GLContext` (given, or its own);
    this class adds the board's image, supersampling and OpenCV's distortion model.

    Args:
        spec: the board.
        pixels_per_square: resolution of the board texture (mipmapped).
        margin_squares: white paper around the board, in squares.
        ctx: a `mvtex.render.context.GLContext` (default: a new one, released by `release`).
    """

    def __init__(self, spec: BoardSpec, pixels_per_square: int = 96, margin_squares: float = 0.5,
                 ctx: GLContext | None = None):
        self.spec = spec
        margin_px = int(round(margin_squares * pixels_per_square))
        image = board_image(spec, pixels_per_square, margin_px)
        # Quad corners in the board frame: the image's outer edges (pixel edges, see board_image);
        # the image's top row (y0) is the texture's first row.
        margin_m = margin_px / pixels_per_square * spec.square_m
        width_m, height_m = spec.size_m
        x0, y0, x1, y1 = -margin_m, -margin_m, width_m + margin_m, height_m + margin_m
        corners = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], dtype=np.float64)
        self._quad = QuadRenderer(image, corners, ctx)
        self._maps: dict[tuple, tuple] = {}

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
        import cv2  # noqa: PLC0415 (loaded on use)

        pose = np.eye(4)
        pose[:3, :] = np.asarray(cam_from_board, dtype=np.float64)[:3, :]
        s = max(1, int(supersample))
        try:
            if np.any(camera.dist != 0):
                pinhole, map_x, map_y = self._distortion_map(camera, s)
                image = cv2.remap(self._quad.draw(pinhole, pose, background), map_x, map_y, cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_CONSTANT, borderValue=background)
            else:
                K = np.diag([s, s, 1.0]) @ camera.K
                K[:2, 2] += (s - 1) / 2.0  # pixel centres of the big image average onto the small one
                image = self._quad.draw(Camera(camera.name, camera.width * s, camera.height * s, K=K, R=np.eye(3),
                                               t=np.zeros(3)), pose, background)
        except ValueError as err:
            raise ValueError(str(err).replace("the quad", "the board")) from None
        if s > 1:
            image = cv2.resize(image, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
        return np.ascontiguousarray(image)

    def _distortion_map(self, camera: Camera, s: int):
        """A pinhole camera covering the distorted image's field at s x the resolution, and
        the (H*s, W*s) float32 maps from distorted pixels into it (cached per camera)."""
        import cv2  # noqa: PLC0415 (loaded on use)

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

    def release(self) -> None:
        """Free this renderer's GL objects, and its context if it made it."""
        self._quad.release()


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
