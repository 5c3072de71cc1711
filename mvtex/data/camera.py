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

from mvtex.util.errors import InputError, OptionError

MAX_IMAGE_SIZE = 16384


MAX_RENDER_PIXELS = 12_000_000
"""Most pixels of one rendered image (12 megapixels, e.g. 4000x3000). Rendering takes
about 140 bytes a pixel (id, barycentric and depth buffers and their readback), so one
image stays within the 2 GB memory target; larger cameras are refused before anything is
allocated. Calibration and rig tools take cameras up to MAX_IMAGE_SIZE a side."""


MAX_COORDINATE_M = 1e6
"""Largest magnitude of a coordinate mvtex accepts, in meters: a camera's translation, a
vertex of a garment or a body (1000 km). Far beyond any rig, it keeps every product and
square mvtex forms finite, and every value it hands the GPU a float32."""


MAX_INTRINSIC_PX = 1e7
"""Largest magnitude of an entry of K (pixels): a focal length of ten million pixels, a
field of view of a tenth of a degree across the largest image."""


MAX_DISTORTION = 1e6
"""Largest magnitude of a distortion coefficient."""


ROTATION_TOLERANCE = 1e-6
"""Largest |R Rᵀ - I| entry and |det R - 1| a camera's rotation may have (a rotation stored
as decimal text in a rig YAML keeps ~1e-15)."""


CAMERA_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


# File and folder names of mvtex's output layouts: a camera's folder must not take one.
RESERVED_NAMES = frozenset({
    "mesh.npz", "texcoords.json", "rig.yaml", "render.json", "overview.png", "dataset.json", "split.json",
    "gt.npy", "inferred.npy", "poses.npy", "config.json", "model.safetensors", "report.json", "summary.json",
    "reconstruction.ply", "comparison.png", "comparison.json", "colmap", "images", "heatmaps",
})


# Names that YAML (the rig format, read by OpenCV) reads as a boolean or null, not as text.
YAML_NON_STRINGS = frozenset({"true", "false", "null"})


def check_camera_name(name) -> str:
    """Return `name` if it is a safe camera name, else raise OptionError (a ValueError) saying why.

    Camera names become folder and file names, so they are restricted to
    ``[A-Za-z0-9][A-Za-z0-9_.-]{0,63}`` (no path separators, no leading dot, so never "."
    or ".."), must not end with a dot, must not be one of the names of mvtex's output
    layouts (`RESERVED_NAMES`, compared without case), and must not be a word YAML reads
    as a boolean or null (`YAML_NON_STRINGS`, without case): a rig file could not store it.
    """
    if not isinstance(name, str) or not CAMERA_NAME.fullmatch(name) or name.endswith("."):
        raise OptionError("camera", f"name {name!r} is not allowed: use 1-64 letters, digits, '_', '-' or '.', "
                          "starting with a letter or digit (it becomes a folder name)")
    if name.lower() in RESERVED_NAMES:
        raise OptionError("camera", f"name {name!r} is reserved (an mvtex output uses that file name)")
    if name.lower() in YAML_NON_STRINGS:
        raise OptionError("camera", f"name {name!r} is not allowed: a rig file (YAML) would read it as "
                          f"{'null' if name.lower() == 'null' else 'a boolean'}, not as a name")
    return name


def check_rotation(R: np.ndarray, what: str = "R") -> None:
    """Raise OptionError unless R (3,3) is a proper rotation: orthonormal (|R Rᵀ - I| ≤
    ROTATION_TOLERANCE entrywise) with determinant +1 (a reflection is not a camera)."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise OptionError(what, f"must be a finite 3x3 rotation matrix, got shape {R.shape}")
    error = float(np.abs(R @ R.T - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if error > ROTATION_TOLERANCE or abs(det - 1.0) > ROTATION_TOLERANCE:
        raise OptionError(what, f"is not a rotation matrix (|R Rᵀ - I| = {error:.3g}, det {det:.6g}; "
                          f"needs orthonormal rows and det +1 within {ROTATION_TOLERANCE:g})")


def _as_float_array(value, what: str) -> np.ndarray:
    """`value` as a float64 array; OptionError (naming `what`) for what is not numbers."""
    if isinstance(value, (str, bytes)) or value is None:
        raise OptionError(what, f"must be an array of numbers, got {type(value).__name__}")
    try:
        return np.array(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise OptionError(what, f"must be an array of numbers, got {type(value).__name__}") from None


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

    Raises:
        OptionError: a name that is not allowed (`check_camera_name`), a size outside
            1..MAX_IMAGE_SIZE, K, R, t or dist not finite numbers of their shape or beyond
            their bounds (`MAX_INTRINSIC_PX`, `MAX_COORDINATE_M`, `MAX_DISTORTION`), K not
            upper triangular with fx, fy > 0, or R not a rotation (`check_rotation`). The rig
            loader and `save_rig` accept exactly these cameras.
    """

    name: str
    width: int
    height: int
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self) -> None:
        # Every check raises OptionError (an InputError, a ValueError): the rig loader and the
        # rig writer accept exactly the cameras this constructor accepts.
        check_camera_name(self.name)
        for key in ("width", "height"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (numbers.Integral, numbers.Real)) \
                    or not np.isfinite(float(value)) or not float(value).is_integer() \
                    or not 1 <= value <= MAX_IMAGE_SIZE:
                raise OptionError("camera", f"{self.name!r}: {key} must be an integer in 1..{MAX_IMAGE_SIZE}, "
                                  f"got {value!r}")
        for key, shape in (("K", (3, 3)), ("R", (3, 3)), ("t", (3,)), ("dist", (5,))):
            value = _as_float_array(getattr(self, key), f"camera {self.name!r}: {key}")
            if key in ("t", "dist"):
                value = value.reshape(-1)
                if key == "dist" and value.size < 5:
                    value = np.pad(value, (0, 5 - value.size))
            if value.shape != shape or not np.all(np.isfinite(value)):
                raise OptionError("camera", f"{self.name!r}: {key} must be finite with shape {shape}, got "
                                  f"{value.shape}{'' if np.all(np.isfinite(value)) else ' with NaN or infinite values'}")
            limit = {"K": MAX_INTRINSIC_PX, "t": MAX_COORDINATE_M, "dist": MAX_DISTORTION}.get(key)
            if limit is not None and np.abs(value).max() > limit:
                unit = {"K": " px", "t": " m"}.get(key, "")
                raise OptionError("camera", f"{self.name!r}: {key} has a value of magnitude {np.abs(value).max():.3g}, "
                                  f"more than {limit:g}{unit}")
            value.setflags(write=False)
            object.__setattr__(self, key, value)
        K = self.K
        if not (K[0, 0] > 0 and K[1, 1] > 0) or K[1, 0] != 0 or np.any(K[2] != (0, 0, 1)):
            raise OptionError("camera", f"{self.name!r}: K must be [[fx,s,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0, "
                              f"got {K.tolist()}")
        check_rotation(self.R, f"camera {self.name!r}: R")
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

    def require_renderable(self, source: str | os.PathLike | None = None) -> None:
        """Raise InputError (naming `source`, e.g. the rig file) unless the camera is pinhole
        (`require_pinhole`) and its image has at most MAX_RENDER_PIXELS pixels: checked
        before a renderer allocates its buffers."""
        self.require_pinhole(source)
        check_render_size(self.width, self.height, source, f"camera {self.name!r}")

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


def check_render_size(width: int, height: int, source: str | os.PathLike | None = None,
                      what: str = "the image") -> None:
    """Raise InputError (naming `source`) when a width x height image has more than
    MAX_RENDER_PIXELS pixels (before any buffer of it is allocated)."""
    if int(width) * int(height) > MAX_RENDER_PIXELS:
        raise InputError(source, f"{what} is {int(width)}x{int(height)} ({int(width) * int(height) / 1e6:.1f} "
                         f"megapixels): mvtex renders images of at most {MAX_RENDER_PIXELS / 1e6:g} megapixels "
                         "(e.g. 4000x3000); render a camera of fewer pixels (K scaled with the size)")


def look_at(name: str, center: Sequence[float], target: Sequence[float], *, width: int, height: int,
            focal: float, up: Sequence[float] = (0.0, 1.0, 0.0)) -> Camera:
    """A camera at `center` looking at `target`, world `up` appearing up in the image.

    The principal point is the image centre ((W-1)/2, (H-1)/2) in OpenCV pixel coordinates.

    Raises:
        OptionError: naming the argument: centre, target or up not finite 3-vectors, the
            target at the centre (no viewing direction), `up` along the viewing direction
            (no roll defined), a focal length that is not a positive finite number, and
            whatever `Camera` refuses (name, width, height).
    """
    check_camera_name(name)
    vectors = {}
    for key, value in (("center", center), ("target", target), ("up", up)):
        vec = _as_float_array(value, key)
        if vec.shape != (3,) or not np.all(np.isfinite(vec)):
            raise OptionError(key, f"must be 3 finite numbers (x, y, z), got {vec.tolist() if vec.size <= 9 else vec.shape}")
        vectors[key] = vec
    if isinstance(focal, bool) or not isinstance(focal, numbers.Real) or not 0 < float(focal) < float("inf"):
        raise OptionError("focal", f"must be a positive finite number of pixels, got {focal!r}")
    center = vectors["center"]
    z = vectors["target"] - center
    distance = float(np.linalg.norm(z))
    if not distance > 1e-12 * max(1.0, float(np.abs(center).max())):
        raise OptionError("target", f"must differ from center (the camera looks from center towards target), "
                          f"both are {center.tolist()}")
    z /= distance
    up_norm = float(np.linalg.norm(vectors["up"]))
    x = np.cross(z, vectors["up"])
    if not up_norm > 0 or np.linalg.norm(x) < 1e-9 * up_norm:
        raise OptionError("up", f"must not be parallel to the viewing direction target - center "
                          f"({z.tolist()}), got {vectors['up'].tolist()}: choose another up vector")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # image y points down: world up appears up
    R = np.stack([x, y, z])
    for key, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not np.isfinite(float(value)):
            raise OptionError(key, f"must be an integer in 1..{MAX_IMAGE_SIZE}, got {value!r}")
    K = np.array([[float(focal), 0.0, (width - 1) / 2.0], [0.0, float(focal), (height - 1) / 2.0], [0.0, 0.0, 1.0]])
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
        import cv2  # noqa: PLC0415 (loaded on use)

        if not 0.0 <= float(alpha) <= 1.0:
            raise OptionError("alpha", f"must be in [0, 1], got {alpha}")
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
    import cv2  # noqa: PLC0415 (loaded on use)

    image = np.asarray(image)
    if image.shape[:2] != (camera.height, camera.width):
        raise ValueError(f"camera {camera.name!r}: image is {image.shape[1]}x{image.shape[0]}, "
                         f"the camera {camera.width}x{camera.height}")
    map_x, map_y = cv2.initUndistortRectifyMap(camera.K, camera.dist, None, pinhole.K,
                                               (pinhole.width, pinhole.height), cv2.CV_32FC1)
    return cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
