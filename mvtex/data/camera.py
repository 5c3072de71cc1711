"""Pinhole cameras and camera rigs, in the OpenCV convention (stated once, here).

    x_cam = R @ X + t            (world -> camera; `cam_from_world`), z forward, y down
    (u, v) = (fx x/z + cx, fy y/z + cy)

Pixel (u, v): u right, v down; the *centre* of the top-left pixel is (0, 0), exactly as
`cv2.projectPoints` computes it. COLMAP puts that centre at (0.5, 0.5); the +0.5 lives only
in `mvtex.formats.colmap`. Units are meters. Rendering needs zero distortion (`dist`).

A rig is stored as an OpenCV FileStorage YAML (`format: "mvtex-rig"`, `version: 1`, a
sequence `cameras` of maps with `name`, `width`, `height`, `K` 3x3, `dist` 1x5, `R` 3x3,
`t` 3x1), read and written with `cv2.FileStorage`.
"""

from __future__ import annotations

import numbers
import os
import re
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from mvtex.util.errors import InputError

MAX_IMAGE_SIZE = 16384


CAMERA_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


# File and folder names of mvtex's output layouts: a camera's folder must not take one.
RESERVED_NAMES = frozenset({
    "mesh.npz", "texcoords.json", "rig.yaml", "render.json", "overview.png", "dataset.json", "split.json",
    "gt.npy", "inferred.npy", "poses.npy", "config.json", "model.safetensors", "report.json", "summary.json",
    "reconstruction.ply", "comparison.png", "comparison.json", "colmap", "images", "heatmaps",
})


def check_camera_name(name) -> str:
    """Return `name` if it is a safe camera name, else raise ValueError saying why.

    Camera names become folder and file names, so they are restricted to
    ``[A-Za-z0-9][A-Za-z0-9_.-]{0,63}`` (no path separators, no leading dot, so never "."
    or ".."), must not end with a dot, and must not be one of the names of mvtex's output
    layouts (`RESERVED_NAMES`, compared without case).
    """
    if not isinstance(name, str) or not CAMERA_NAME.fullmatch(name) or name.endswith("."):
        raise ValueError(f"camera name {name!r} is not allowed: use 1-64 letters, digits, '_', '-' or '.', "
                         "starting with a letter or digit (it becomes a folder name)")
    if name.lower() in RESERVED_NAMES:
        raise ValueError(f"camera name {name!r} is reserved (an mvtex output uses that file name)")
    return name


def image_contains(pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """(...,) bool: which pixel positions (..., 2) lie on a width x height image, i.e. within
    the outer edges of the border pixels (u in (-0.5, W - 0.5), v in (-0.5, H - 0.5)); NaN is
    outside."""
    u, v = pixels[..., 0], pixels[..., 1]
    return (u > -0.5) & (u < width - 0.5) & (v > -0.5) & (v < height - 0.5)


@dataclass(frozen=True)
class Camera:
    """A pinhole camera.

    Attributes:
        name: unique name within a rig (used for folder names).
        width, height: image size in pixels.
        K: (3,3) float64 intrinsics [[fx,0,cx],[0,fy,cy],[0,0,1]].
        R: (3,3) float64 rotation, world -> camera.
        t: (3,) float64 translation, world -> camera.
        dist: (5,) float64 OpenCV distortion (k1,k2,p1,p2,k3); must be zero to render.
    """

    name: str
    width: int
    height: int
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self) -> None:
        check_camera_name(self.name)
        for key in ("width", "height"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (numbers.Integral, numbers.Real)) \
                    or not float(value).is_integer() or not 1 <= value <= MAX_IMAGE_SIZE:
                raise ValueError(f"camera {self.name!r}: {key} must be an integer in 1..{MAX_IMAGE_SIZE}, got {value!r}")
        for key, shape in (("K", (3, 3)), ("R", (3, 3)), ("t", (3,)), ("dist", (5,))):
            value = np.asarray(getattr(self, key), dtype=np.float64)
            if key in ("t", "dist"):
                value = value.reshape(-1)
                if key == "dist" and value.size < 5:
                    value = np.pad(value, (0, 5 - value.size))
            if value.shape != shape or not np.all(np.isfinite(value)):
                raise ValueError(f"camera {self.name!r}: {key} must be finite with shape {shape}, got {value.shape}")
            value.setflags(write=False)
            object.__setattr__(self, key, value)
        K = self.K
        if not (K[0, 0] > 0 and K[1, 1] > 0) or K[1, 0] != 0 or np.any(K[2] != (0, 0, 1)):
            raise ValueError(f"camera {self.name!r}: K must be [[fx,s,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0, "
                             f"got {K.tolist()}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    # -- geometry -------------------------------------------------------------------------
    @property
    def cam_from_world(self) -> np.ndarray:
        """(3,4) float64 [R | t]."""
        return np.hstack([self.R, self.t[:, None]])

    @property
    def projection(self) -> np.ndarray:
        """(3,4) float64 P = K [R | t], pixels in the OpenCV convention."""
        return self.K @ self.cam_from_world

    @property
    def center(self) -> np.ndarray:
        """(3,) float64 camera centre in world coordinates, -R^T t."""
        return -self.R.T @ self.t

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> camera coordinates (..., 3), float64."""
        return np.asarray(points, dtype=np.float64) @ self.R.T + self.t

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points (..., 3).

        Returns:
            pixels (..., 2) float64 in OpenCV pixel coordinates (ignores `dist`), and
            depth (..., ) float64 camera-space z (meters).
        """
        x = self.to_camera(points)
        z = x[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = x[..., :2] / z[..., None]
        pixels = uv * np.array([self.K[0, 0], self.K[1, 1]]) + np.array([self.K[0, 2], self.K[1, 2]])
        pixels[..., 0] += self.K[0, 1] * uv[..., 1]
        return pixels, z

    def in_image(self, pixels: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """(...,) bool: in front of the camera (depth > 0) and inside the image, i.e. within
        the outer edges of the border pixels (u in (-0.5, W - 0.5), v in (-0.5, H - 0.5)).

        Args:
            pixels: (..., 2) float pixel coordinates and depth (...,) camera-space z, as
                returned by `project`.
        """
        return (depth > 0) & image_contains(pixels, self.width, self.height)

    def require_pinhole(self, source: str | os.PathLike | None = None) -> None:
        """Raise InputError (naming `source`, e.g. the rig file) unless `dist` is all zero:
        rendering, sliding and COLMAP export need undistorted (pinhole) cameras."""
        if np.any(self.dist != 0):
            raise InputError(source, f"camera {self.name!r} has non-zero distortion {self.dist.tolist()}: "
                             "mvtex renders pinhole cameras: use the pinhole rig of the same K "
                             "(mvtex rig RIG --undistort --out RIG2) and compare with undistorted images "
                             "(mvtex undistort IMAGES --rig RIG --out DIR)")

    def sees(self, points: np.ndarray) -> bool:
        """True if any world point (..., 3) lies in front of the camera and inside its image."""
        pixels, z = self.project(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        with np.errstate(invalid="ignore"):
            return bool(np.any(self.in_image(pixels, z)))

    def pixel_rays(self, pixels: np.ndarray) -> np.ndarray:
        """Unit ray directions (..., 3) float64 in world coordinates through pixels (..., 2)."""
        pixels = np.asarray(pixels, dtype=np.float64)
        homog = np.concatenate([pixels, np.ones(pixels.shape[:-1] + (1,))], axis=-1)
        d_cam = homog @ np.linalg.inv(self.K).T
        d_world = d_cam @ self.R
        return d_world / np.linalg.norm(d_world, axis=-1, keepdims=True)

    def with_name(self, name: str) -> "Camera":
        return replace(self, name=name)


def look_at(name: str, center: Sequence[float], target: Sequence[float], *, width: int, height: int,
            focal: float, up: Sequence[float] = (0.0, 1.0, 0.0)) -> Camera:
    """A camera at `center` looking at `target`, world `up` appearing up in the image.

    The principal point is the image centre ((W-1)/2, (H-1)/2) in OpenCV pixel coordinates.
    """
    center = np.asarray(center, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - center
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # image y points down: world up appears up
    R = np.stack([x, y, z])
    K = np.array([[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return Camera(name=name, width=width, height=height, K=K, R=R, t=-R @ center)


def undistorted_camera(camera: Camera, alpha: float | None = None) -> Camera:
    """The pinhole camera (zero `dist`) that sees the undistorted images of `camera`.

    Args:
        camera: a camera, possibly with distortion.
        alpha: None keeps K (the undistorted image is the pinhole image of the same K, what
            mvtex renders); a number in [0, 1] takes K from `cv2.getOptimalNewCameraMatrix`
            (0: every output pixel sees the scene, the borders are cropped; 1: every input
            pixel is kept, black corners appear).

    Returns:
        The same camera with the new K and zero distortion (same name, size and pose).
    """
    if alpha is None:
        K = camera.K
    else:
        import cv2

        if not 0.0 <= float(alpha) <= 1.0:
            raise ValueError(f"alpha must be in [0, 1], got {alpha}")
        size = (camera.width, camera.height)
        K, _ = cv2.getOptimalNewCameraMatrix(camera.K, camera.dist, size, float(alpha), size)
    return replace(camera, K=np.asarray(K, dtype=np.float64), dist=np.zeros(5))


def undistort_image(image: np.ndarray, camera: Camera, pinhole: Camera) -> np.ndarray:
    """Resample an image of `camera` into the pinhole camera `pinhole` (same pose) with
    `cv2.initUndistortRectifyMap` and `cv2.remap` (bilinear; black outside the input).

    Args:
        image: (H,W) or (H,W,C) image of `camera`, H, W its size.
        camera: the camera that took it (with its distortion).
        pinhole: the output camera, zero distortion (e.g. `undistorted_camera(camera)`).

    Returns:
        (pinhole.height, pinhole.width[, C]) image of the same dtype.
    """
    import cv2

    image = np.asarray(image)
    if image.shape[:2] != (camera.height, camera.width):
        raise ValueError(f"camera {camera.name!r}: image is {image.shape[1]}x{image.shape[0]}, "
                         f"the camera {camera.width}x{camera.height}")
    map_x, map_y = cv2.initUndistortRectifyMap(camera.K, camera.dist, None, pinhole.K,
                                               (pinhole.width, pinhole.height), cv2.CV_32FC1)
    return cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
