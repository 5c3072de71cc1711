"""ChArUco calibration boards: the SPEC string, the printable image, corner detection, and
a moderngl renderer of the board seen by a camera (synthetic calibration images).

A board SPEC reads `charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT`, e.g.
`charuco:9x6:0.05:0.0375:DICT_5X5_100`: COLS x ROWS chessboard squares of SQUARE_M meters,
ArUco markers of MARKER_M meters from the OpenCV dictionary DICT (`cv2.aruco.DICT_*`).

Board frame (OpenCV's `CharucoBoard`): origin at the board's top-left outer corner, x along
the columns, y down the rows, z = 0 on the board (into the board, away from a camera that
sees its printed side). Chessboard corner `i` (the ids `CharucoDetector` reports) is at
((i mod (COLS-1)) + 1, (i div (COLS-1)) + 1) * SQUARE_M.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from .camera import Camera
from .errors import InputError

SPEC_PATTERN = re.compile(r"^charuco:(\d+)x(\d+):([0-9.eE+-]+):([0-9.eE+-]+):(DICT_\w+)$")
SPEC_FORMAT = "charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT (e.g. charuco:9x6:0.05:0.0375:DICT_5X5_100)"
PNG_SOFTWARE = "mvtex board"
MM_PER_INCH = 25.4


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board.

    Attributes:
        cols, rows: number of chessboard squares along x and y (each >= 3).
        square_m: side of a chessboard square in meters.
        marker_m: side of an ArUco marker in meters (< square_m).
        dictionary: name of an OpenCV predefined dictionary, e.g. "DICT_5X5_100".
    """

    cols: int
    rows: int
    square_m: float
    marker_m: float
    dictionary: str

    def __str__(self) -> str:
        return f"charuco:{self.cols}x{self.rows}:{self.square_m:g}:{self.marker_m:g}:{self.dictionary}"

    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) of the chessboard area in meters."""
        return self.cols * self.square_m, self.rows * self.square_m

    @property
    def num_corners(self) -> int:
        """Number of inner chessboard corners, (COLS-1)(ROWS-1)."""
        return (self.cols - 1) * (self.rows - 1)

    @cached_property
    def cv_board(self):
        """The `cv2.aruco.CharucoBoard`."""
        import cv2

        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_m, self.marker_m, dictionary)

    @property
    def corners(self) -> np.ndarray:
        """(num_corners, 3) float64 chessboard corners in the board frame, indexed by corner id."""
        return np.asarray(self.cv_board.getChessboardCorners(), dtype=np.float64).reshape(-1, 3)


def parse_board_spec(text: str) -> BoardSpec:
    """Parse `charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT`; anything else raises InputError."""
    import cv2

    match = SPEC_PATTERN.match(str(text).strip())
    if not match:
        raise InputError(None, f"board SPEC {text!r} does not parse; expected {SPEC_FORMAT}")
    cols, rows = int(match[1]), int(match[2])
    try:
        square, marker = float(match[3]), float(match[4])
    except ValueError:
        raise InputError(None, f"board SPEC {text!r}: square and marker sizes must be numbers in meters") from None
    name = match[5]
    if cols < 3 or rows < 3:
        raise InputError(None, f"board SPEC {text!r}: needs at least 3x3 squares, got {cols}x{rows}")
    if not (np.isfinite(square) and np.isfinite(marker) and 0 < marker < square):
        raise InputError(None, f"board SPEC {text!r}: needs 0 < MARKER_M < SQUARE_M, got {marker:g} and {square:g}")
    if not hasattr(cv2.aruco, name):
        raise InputError(None, f"board SPEC {text!r}: unknown dictionary {name} (OpenCV's cv2.aruco.DICT_*, "
                         "e.g. DICT_4X4_50, DICT_5X5_100, DICT_6X6_250)")
    try:
        size = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)).bytesList.shape[0]
    except (cv2.error, TypeError):
        raise InputError(None, f"board SPEC {text!r}: {name} is not a predefined ArUco dictionary") from None
    needed = (cols * rows) // 2
    if needed > size:
        raise InputError(None, f"board SPEC {text!r}: {cols}x{rows} squares need {needed} markers, {name} has {size}")
    return BoardSpec(cols, rows, square, marker, name)


# -- the printable image ------------------------------------------------------------------

def board_image(spec: BoardSpec, pixels_per_square: int, margin_px: int = 0) -> np.ndarray:
    """The board as a gray image, white margin around it.

    Args:
        spec: the board.
        pixels_per_square: side of a chessboard square in pixels.
        margin_px: white border added on every side.

    Returns:
        (rows*pps + 2*margin, cols*pps + 2*margin) uint8. Board point (x, y) in meters lies at
        OpenCV pixel (x/square*pps + margin - 0.5, y/square*pps + margin - 0.5): square
        edges fall on pixel edges.
    """
    pps = int(pixels_per_square)
    if pps < 8:
        raise ValueError(f"pixels_per_square must be >= 8, got {pps}")
    size = (spec.cols * pps + 2 * margin_px, spec.rows * pps + 2 * margin_px)
    return np.asarray(spec.cv_board.generateImage(size, marginSize=int(margin_px), borderBits=1), dtype=np.uint8)


def write_board_png(spec: BoardSpec, path: str | os.PathLike, *, dpi: float | None = None,
                    pixels_per_square: int | None = None, margin_m: float | None = None) -> dict:
    """Write the printable board as a PNG that records its print resolution.

    Give `dpi` (pixels per inch of the print; default 300) or `pixels_per_square`. The PNG
    carries its dpi (pHYs), so printing it at 100 % scale gives squares of `square_m`; the
    margin (default: half a square, at least 10 mm) shows the SPEC in small print. A file
    at `path` is only replaced if mvtex wrote it.

    Returns:
        {"path", "spec", "pixels_per_square", "dpi", "width_px", "height_px", "width_mm", "height_mm"}.
    """
    import cv2
    from PIL import Image, PngImagePlugin

    from .io import atomic_path

    path = Path(path)
    if dpi is not None and pixels_per_square is not None:
        raise InputError(None, "give either dpi or pixels_per_square, not both")
    if pixels_per_square is None:
        dpi = 300.0 if dpi is None else float(dpi)
        if not (np.isfinite(dpi) and dpi > 0):
            raise InputError(None, f"dpi must be positive, got {dpi}")
        pixels_per_square = int(round(spec.square_m * 1000 / MM_PER_INCH * dpi))
    else:
        dpi = pixels_per_square / (spec.square_m * 1000 / MM_PER_INCH)
    if pixels_per_square < 8:
        raise InputError(None, f"{pixels_per_square} pixels per square is too few to print the markers (>= 8)")
    margin_m = max(spec.square_m / 2, 0.010) if margin_m is None else float(margin_m)
    margin_px = int(round(margin_m * 1000 / MM_PER_INCH * dpi))
    image = board_image(spec, pixels_per_square, margin_px)
    text = f"{spec}   square {spec.square_m * 1000:g} mm   print at {dpi:.0f} dpi, 100 %"
    scale = margin_px * 0.35 / 22.0
    if scale >= 0.25:
        (w, h), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
        if w < image.shape[1] - 2 * margin_px:
            y = image.shape[0] - margin_px // 2 + h // 2
            cv2.putText(image, text, (margin_px, y), cv2.FONT_HERSHEY_SIMPLEX, scale, 96,
                        max(1, int(round(scale * 2))), cv2.LINE_AA)
    _check_overwritable_png(path)
    info = PngImagePlugin.PngInfo()
    info.add_text("Software", PNG_SOFTWARE)
    info.add_text("Description", str(spec))
    with atomic_path(path) as tmp:
        Image.fromarray(image).save(tmp, format="PNG", dpi=(dpi, dpi), pnginfo=info)
    height, width = image.shape
    return {"path": str(path), "spec": str(spec), "pixels_per_square": int(pixels_per_square), "dpi": float(dpi),
            "width_px": int(width), "height_px": int(height),
            "width_mm": width / dpi * MM_PER_INCH, "height_mm": height / dpi * MM_PER_INCH}


def _check_overwritable_png(path: Path) -> None:
    if not path.exists():
        return
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as existing:
            software = existing.info.get("Software", "")
    except (UnidentifiedImageError, OSError):
        software = ""
    if software != PNG_SOFTWARE:
        raise InputError(path, "exists and was not written by mvtex board; not overwriting it")


# -- detection ----------------------------------------------------------------------------

@dataclass(frozen=True)
class Detection:
    """Chessboard corners of a board found in one image.

    Attributes:
        ids: (k,) int32 corner ids (rows of `BoardSpec.corners`), ascending.
        pixels: (k,2) float64 OpenCV pixel coordinates, sub-pixel.
    """

    ids: np.ndarray
    pixels: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


class BoardDetector:
    """`cv2.aruco.CharucoDetector` for one board, made once and reused over images."""

    def __init__(self, spec: BoardSpec):
        import cv2

        self.spec = spec
        charuco = cv2.aruco.CharucoParameters()
        detector = cv2.aruco.DetectorParameters()
        detector.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        self._detector = cv2.aruco.CharucoDetector(spec.cv_board, charuco, detector)

    def detect(self, image: np.ndarray) -> Detection:
        """Detect the chessboard corners in a gray (H,W) or colour (H,W,3) uint8 image."""
        import cv2

        image = np.asarray(image)
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        corners, ids, _, _ = self._detector.detectBoard(image)
        if ids is None or len(ids) == 0:
            return Detection(np.zeros(0, np.int32), np.zeros((0, 2)))
        ids = np.asarray(ids, dtype=np.int32).reshape(-1)
        pixels = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
        order = np.argsort(ids)
        return Detection(ids[order], pixels[order])


# -- synthetic images ---------------------------------------------------------------------

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

    `mvtex.raster.render_textured` shades meshes with the built-in fabric texture only, so
    the board quad has its own small program here; the projection is the shared
    `mvtex.raster.clip_from_camera`, so rendered pixels follow the OpenCV convention.

    It draws in a `mvtex.raster.GLContext` (given, or its own), made current for each draw
    as the rasterizer does, so it shares a process with other contexts.
    """

    def __init__(self, spec: BoardSpec, pixels_per_square: int = 96, margin_squares: float = 0.5,
                 ctx=None):
        """
        Args:
            spec: the board.
            pixels_per_square: resolution of the board texture (mipmapped).
            margin_squares: white paper around the board, in squares.
            ctx: a `mvtex.raster.GLContext` (default: a new one, released by `release`).
        """
        import moderngl

        from .raster import GLContext

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
        import moderngl

        from .raster import clip_from_camera

        z = self._quad_corners @ pose[2, :3] + pose[2, 3]
        if z.min() <= 0:
            raise ValueError(f"camera {camera.name!r}: the board is (partly) behind the camera")
        near, far = max(1e-3, 0.5 * float(z.min())), 2.0 * float(z.max()) + 1e-3
        with self.ctx:
            return self._draw_current(camera, pose, background, near, far)

    def _draw_current(self, camera: Camera, pose: np.ndarray, background: int, near: float, far: float) -> np.ndarray:
        import moderngl

        from .raster import clip_from_camera

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

    from .io import save_png

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
