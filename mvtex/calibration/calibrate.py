"""Calibrate a camera array from images of a ChArUco board.

Input layout: `IMAGES/<camera>/<frame>.png|jpg`; files with the same frame name in
different camera folders were taken at the same instant (the board did not move).

Steps:
1. Detect the chessboard corners in every image (`mvtex.calibration.board.BoardDetector`). A camera's
   frame with fewer than `min_corners` corners, or with all corners on one line, is
   skipped and counted.
2. Per camera, intrinsics and distortion with `cv2.calibrateCamera` (which also gives the
   board pose in each of its frames).
3. Initial extrinsics: walk the graph of cameras that share frames, from the reference
   camera outwards, averaging the relative pose over the shared frames.
4. Joint bundle adjustment (`scipy.optimize.least_squares`, sparse Jacobian pattern, Huber
   loss of 1 px) over every camera's intrinsics, distortion and pose (the reference camera's
   pose stays the identity: the rig's world frame is the reference camera's frame) and
   every frame's board pose.

OpenCV 5's `cv2.calibrateMultiview` takes one set of board points per frame, shared by all
cameras, and a detection mask per camera and frame (none per point); ChArUco detections
are partial and differ between cameras (corners hidden or out of the image), so the joint
step is the bundle adjustment above. Distortion follows OpenCV's
5-coefficient model (k1, k2, p1, p2, k3), as `cv2.projectPoints` computes it.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from mvtex.calibration.board import BoardDetector, BoardSpec, Detection
from mvtex.calibration.images import CameraImages, camera_image_size, read_gray
from mvtex.calibration.options import CalibrateOptions
from mvtex.data.camera import Camera
from mvtex.data.rig import Rig
from mvtex.util.checks import as_list, check_instance
from mvtex.util.errors import InputError, OptionError

CALIBRATION_FORMAT = "mvtex-calibration"


MIN_FRAMES = 3


@dataclass(frozen=True)
class Observations:
    """One camera's usable corner detections over the frames.

    Attributes:
        frames: (k,) frame names with a usable detection.
        detections: (k,) `Detection` per frame, same order.
        skipped: frame names where the board was missing or too little of it was seen.
        image_size: (width, height) in pixels.
    """

    frames: tuple[str, ...]
    detections: tuple[Detection, ...]
    skipped: tuple[str, ...]
    image_size: tuple[int, int]


@dataclass(frozen=True)
class Calibration:
    """A calibrated rig and what it was made from.

    Attributes:
        rig: the cameras, world frame = the reference camera's frame, sorted by name.
        reference: the reference camera's name.
        board: the board.
        frames: (f,) names of the frames used (seen by at least one camera).
        world_from_board: (f,4,4) float64 board pose of each frame in the rig's world frame.
        observations: camera -> its usable detections.
        residuals: camera -> (k_c, 2) float64 reprojection residuals (projected - detected,
            pixels) of its corners, in the order of its detections concatenated.
        rms_px: root mean square reprojection error over every corner of every camera.
        options: the options that made it.
    """

    rig: Rig
    reference: str
    board: BoardSpec
    frames: tuple[str, ...]
    world_from_board: np.ndarray
    observations: dict[str, Observations]
    residuals: dict[str, np.ndarray]
    rms_px: float
    options: CalibrateOptions | None = field(repr=False, default=None)

    def camera_rms_px(self, name: str) -> float:
        r = self.residuals[name]
        return float(np.sqrt(np.mean(np.sum(r ** 2, axis=1)))) if len(r) else float("nan")

    def frame_rms_px(self, name: str) -> dict[str, float]:
        """Camera `name`'s RMS reprojection error per frame (pixels): find the bad frames."""
        obs, r = self.observations[name], self.residuals[name]
        ends = np.cumsum([len(d) for d in obs.detections])
        return {frame: float(np.sqrt(np.mean(np.sum(part ** 2, axis=1))))
                for frame, part in zip(obs.frames, np.split(r, ends[:-1]))}

    def summary(self) -> dict:
        """The JSON of `mvtex calibrate --json` (DESIGN §7), plus skipped frame counts."""
        return {"num_cameras": len(self.rig), "num_frames": len(self.frames), "rms_reprojection_px": self.rms_px,
                "reference": self.reference,
                "per_camera": {name: {"rms_px": self.camera_rms_px(name), "frames": len(obs.frames),
                                      "skipped": len(obs.skipped)}
                               for name, obs in self.observations.items()}}


def detect_camera(images: CameraImages, detector: BoardDetector, min_corners: int, progress=None) -> Observations:
    """Detect the board in every frame of one camera; keep frames with enough spread corners."""
    frames, detections, skipped = [], [], []
    size = camera_image_size(images)  # from the headers: an odd image is named before any is decoded
    corners = detector.spec.corners
    for frame, path in images.files.items():
        image = read_gray(path)
        if size != (image.shape[1], image.shape[0]):  # its EXIF orientation turns it
            raise InputError(path, f"image is {image.shape[1]}x{image.shape[0]} once turned as its EXIF "
                             f"orientation says, camera {images.name}'s other images are {size[0]}x{size[1]}")
        detection = detector.detect(image)
        if len(detection) >= min_corners and _spread(corners[detection.ids]):
            frames.append(frame)
            detections.append(detection)
        else:
            skipped.append(frame)
        if progress is not None:
            progress.update(1)
    return Observations(tuple(frames), tuple(detections), tuple(skipped), size)


def _spread(points: np.ndarray) -> bool:
    """True unless the board points lie on one line (no homography from them)."""
    centred = points[:, :2] - points[:, :2].mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False)
    return bool(s[-1] > 1e-6 * max(s[0], 1e-12))


def _intrinsic_flags(distortion: str) -> int:
    import cv2  # noqa: PLC0415 (loaded on use)

    flags = 0
    if "k3" not in distortion:
        flags |= cv2.CALIB_FIX_K3
    if "p1" not in distortion:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    if distortion == "none":
        flags |= cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2
    return flags


def _dist_free(distortion: str) -> np.ndarray:
    """Indices of the free distortion coefficients in (k1, k2, p1, p2, k3)."""
    names = ("k1", "k2", "p1", "p2", "k3")
    return np.array([i for i, name in enumerate(names) if name in distortion], dtype=int)


def calibrate_intrinsics(obs: Observations, spec: BoardSpec, distortion: str) -> tuple[np.ndarray, np.ndarray, float, list]:
    """`cv2.calibrateCamera` on one camera's detections.

    OpenCV's own start (`initCameraMatrix2D`) can land far from the focal length when few
    views are strongly tilted, and the optimisation then stalls in a wrong minimum; so the
    calibration also starts from the focal length that best explains the views with the
    principal point at the image centre (a scan, `_scan_focal`), and the lower RMS wins.

    Returns:
        K (3,3), dist (5,), RMS (px), and the cam_from_board (4,4) of each of its frames.
    """
    import cv2  # noqa: PLC0415 (loaded on use)

    corners = spec.corners
    object_points = [corners[d.ids].astype(np.float32) for d in obs.detections]
    image_points = [d.pixels.astype(np.float32) for d in obs.detections]
    flags = _intrinsic_flags(distortion)
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    guess = _scan_focal(object_points, image_points, obs.image_size)
    best = None
    for start, extra in ((None, 0), (guess, cv2.CALIB_USE_INTRINSIC_GUESS)):
        result = cv2.calibrateCamera(object_points, image_points, obs.image_size,
                                     None if start is None else start.copy(), None if start is None else np.zeros(5),
                                     flags=flags | extra, criteria=criteria)
        if best is None or result[0] < best[0]:
            best = result
    rms, K, dist, rvecs, tvecs = best[:5]
    poses = [_pose(np.asarray(r).reshape(3), np.asarray(t).reshape(3)) for r, t in zip(rvecs, tvecs)]
    return np.asarray(K, np.float64), np.asarray(dist, np.float64).reshape(-1)[:5], float(rms), poses


def _scan_focal(object_points: list, image_points: list, image_size: tuple[int, int]) -> np.ndarray:
    """(3,3) K with the principal point at the image centre and the focal length (from
    0.2 to 5 image diagonals) under which per-view planar PnP reprojects best."""
    import cv2  # noqa: PLC0415 (loaded on use)

    width, height = image_size
    diagonal = float(np.hypot(width, height))
    best_error, best_K = np.inf, None  # replaced on the first focal length: errors are finite
    for focal in diagonal * np.geomspace(0.2, 5.0, 48):
        K = np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1.0]])
        error = 0.0
        for obj, img in zip(object_points, image_points):
            ok, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_IPPE)
            if not ok or np.size(rvec) != 3 or np.size(tvec) != 3:
                error += 1e6 * len(obj)  # a failed view counts as a very poor fit
                continue
            projected, _ = cv2.projectPoints(obj, rvec, tvec, K, None)
            error += float(np.sum((projected.reshape(-1, 2) - img) ** 2))
        if error < best_error:
            best_error, best_K = error, K
    return best_K


def _pose(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rvec).as_matrix()
    T[:3, 3] = tvec
    return T


def _inverse(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def _average_pose(poses: Sequence[np.ndarray]) -> np.ndarray:
    """Rotation mean (chordal) and median translation of rigid transforms (4,4)."""

    T = np.eye(4)
    T[:3, :3] = Rotation.from_matrix(np.stack([p[:3, :3] for p in poses])).mean().as_matrix()
    T[:3, 3] = np.median(np.stack([p[:3, 3] for p in poses]), axis=0)
    return T


def initial_extrinsics(names: Sequence[str], reference: str, frames: dict[str, list[str]],
                       board_poses: dict[str, dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """cam_from_reference (4,4) of every camera, by a breadth-first walk from `reference`
    over cameras that share frames, each step averaged over the shared frames.

    Raises:
        InputError: a camera shares no frame with the others, or a group of cameras is
            not linked to the reference's group by shared frames.
    """
    shared = {a: {b: sorted(set(frames[a]) & set(frames[b])) for b in names if b != a} for a in names}
    if len(names) > 1:
        for name in names:
            if not any(shared[name].values()):
                listed = ", ".join(frames[name][:5]) + (", ..." if len(frames[name]) > 5 else "")
                raise InputError(None, f"camera {name} shares no frame with the other cameras (the board is found "
                                 f"in its frames {listed}, but in none of those of another camera)")
    cam_from_ref = {reference: np.eye(4)}
    queue = [reference]
    while queue:
        parent = queue.pop(0)
        # Visit the best-linked cameras first so each pose comes from the most shared frames.
        for child in sorted(names, key=lambda c: -len(shared[parent].get(c, []))):
            if child in cam_from_ref or not shared[parent].get(child):
                continue
            child_from_parent = _average_pose([board_poses[child][f] @ _inverse(board_poses[parent][f])
                                               for f in shared[parent][child]])
            cam_from_ref[child] = child_from_parent @ cam_from_ref[parent]
            queue.append(child)
    missing = [n for n in names if n not in cam_from_ref]
    if missing:
        raise InputError(None, f"cameras {', '.join(missing)} share no frame, directly or through other cameras, "
                         f"with the reference camera {reference}")
    return cam_from_ref


def project_distorted(points: np.ndarray, rotvec: np.ndarray, tvec: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """OpenCV's pinhole + 5-coefficient distortion projection, as `cv2.projectPoints`.

    Args:
        points: (N,3) points in the frame the pose maps from.
        rotvec, tvec: (3,) camera_from_frame (Rodrigues vector, translation).
        intrinsics: (9,) fx, fy, cx, cy, k1, k2, p1, p2, k3.

    Returns:
        (N,2) float64 pixels.
    """
    camera = np.asarray(points, np.float64) @ _matrices(np.asarray(rotvec, np.float64)[None])[0].T + tvec
    return _distort_project(camera, np.broadcast_to(np.asarray(intrinsics, np.float64), (len(camera), 9)))


def _matrices(rotvecs: np.ndarray) -> np.ndarray:
    """(k,3) Rodrigues vectors -> (k,3,3) rotation matrices."""

    return Rotation.from_rotvec(rotvecs).as_matrix().reshape(-1, 3, 3)


def _distort_project(camera: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """Camera-frame points (N,3) and per-point intrinsics (N,9) -> (N,2) pixels."""
    xn = camera[:, 0] / camera[:, 2]
    yn = camera[:, 1] / camera[:, 2]
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = intrinsics.T
    r2 = xn * xn + yn * yn
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
    return np.stack([fx * xd + cx, fy * yd + cy], axis=1)


class _Problem:
    """Parameter layout and residuals of the joint bundle adjustment.

    Parameters, in order: per camera its free intrinsics (fx, fy, cx, cy and the free
    distortion coefficients); per non-reference camera its cam_from_world (rotvec, t); per
    frame its world_from_board (rotvec, t).
    """

    def __init__(self, names, reference, frame_names, free_dist, cam_index, frame_index, points, pixels):
        self.names, self.reference, self.frame_names = list(names), reference, list(frame_names)
        self.free_dist = free_dist
        self.n_intr = 4 + len(free_dist)
        self.cam_index, self.frame_index = cam_index, frame_index
        self.points, self.pixels = points, pixels
        self.moving = [n for n in self.names if n != reference]
        self.pose_slot = {n: i for i, n in enumerate(self.moving)}
        self.o_pose = len(self.names) * self.n_intr
        self.o_frame = self.o_pose + 6 * len(self.moving)
        self.size = self.o_frame + 6 * len(self.frame_names)
        ref = self.names.index(reference)
        # Row in the per-camera pose table: the reference camera reads a fixed zero pose.
        self.pose_row = np.array([len(self.moving) if i == ref else self.pose_slot[n]
                                  for i, n in enumerate(self.names)])[cam_index]

    def pack(self, intrinsics: dict[str, np.ndarray], cam_from_world: dict[str, np.ndarray],
             world_from_board: np.ndarray) -> np.ndarray:

        x = np.zeros(self.size)
        for i, name in enumerate(self.names):
            full = intrinsics[name]
            x[i * self.n_intr:(i + 1) * self.n_intr] = np.concatenate([full[:4], full[4:][self.free_dist]])
        for name in self.moving:
            T = cam_from_world[name]
            j = self.o_pose + 6 * self.pose_slot[name]
            x[j:j + 3] = Rotation.from_matrix(T[:3, :3]).as_rotvec()
            x[j + 3:j + 6] = T[:3, 3]
        for f, T in enumerate(world_from_board):
            j = self.o_frame + 6 * f
            x[j:j + 3] = Rotation.from_matrix(T[:3, :3]).as_rotvec()
            x[j + 3:j + 6] = T[:3, 3]
        return x

    def intrinsics(self, x: np.ndarray) -> np.ndarray:
        """(cameras, 9) fx, fy, cx, cy, k1, k2, p1, p2, k3."""
        table = np.zeros((len(self.names), 9))
        block = x[:self.o_pose].reshape(len(self.names), self.n_intr)
        table[:, :4] = block[:, :4]
        table[:, 4 + self.free_dist] = block[:, 4:]
        return table

    def poses(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(moving + 1, 6) camera poses (last row: the reference's zero) and (frames, 6)."""
        cams = np.vstack([x[self.o_pose:self.o_frame].reshape(-1, 6), np.zeros((1, 6))])
        return cams, x[self.o_frame:].reshape(-1, 6)

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """(2N,) projected - detected pixels, x and y interleaved."""
        cams, boards = self.poses(x)
        board_R, cam_R = _matrices(boards[:, :3]), _matrices(cams[:, :3])
        world = np.einsum("nij,nj->ni", board_R[self.frame_index], self.points) + boards[self.frame_index, 3:]
        camera = np.einsum("nij,nj->ni", cam_R[self.pose_row], world) + cams[self.pose_row, 3:]
        projected = _distort_project(camera, self.intrinsics(x)[self.cam_index])
        return (projected - self.pixels).reshape(-1)

    def sparsity(self):
        """(2N, size) 0/1 pattern: which parameters each residual depends on."""

        n = len(self.points)
        columns = [self.cam_index[:, None] * self.n_intr + np.arange(self.n_intr),
                   self.o_frame + 6 * self.frame_index[:, None] + np.arange(6)]
        moving = self.pose_row < len(self.moving)
        pose_columns = self.o_pose + 6 * self.pose_row[:, None] + np.arange(6)
        rows, cols = [], []
        for block, keep in ((columns[0], slice(None)), (columns[1], slice(None)), (pose_columns, moving)):
            point = np.arange(n)[keep]
            block = block[keep]
            for axis in (0, 1):
                rows.append(np.repeat(2 * point + axis, block.shape[1]))
                cols.append(block.reshape(-1))
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        return coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(2 * n, self.size)).tocsr()


def calibrate(cameras: Sequence[CameraImages], options: CalibrateOptions, *, progress: bool = True) -> Calibration:
    """Calibrate every camera and the rig (see the module docstring).

    Args:
        cameras: from `find_images`.
        options: board, reference camera, distortion model, thresholds.
        progress: show a progress bar over the images (stderr).

    Returns:
        The calibration; its rig's world frame is the reference camera's frame.

    Raises:
        InputError: unreadable images, a camera with too few usable frames, a camera that
            shares no frame with the others, an unknown reference camera.
    """

    check_instance(options, CalibrateOptions, "options")

    cameras = as_list(cameras, "cameras", CameraImages, "CameraImages (`find_images`)")
    if not cameras:
        raise OptionError("cameras", "must be a non-empty list of CameraImages (`find_images`)")
    import cv2  # noqa: PLC0415 (loaded on use)

    names = [c.name for c in cameras]
    root = next(iter(cameras[0].files.values())).parent.parent
    reference = options.reference or names[0]
    if reference not in names:
        raise InputError(root, f"no camera named {reference} (the image folder has {', '.join(names)})")
    detector = BoardDetector(options.board)
    total = sum(len(c.files) for c in cameras)
    observations: dict[str, Observations] = {}
    with tqdm(total=total, desc="detect", unit="image", disable=not progress, file=sys.stderr) as bar:
        for images in cameras:
            observations[images.name] = detect_camera(images, detector, options.min_corners, bar)
    for images in cameras:
        obs = observations[images.name]
        if len(obs.frames) < MIN_FRAMES:
            folder = next(iter(images.files.values())).parent
            what = "the board is never found" if not obs.frames else f"the board is found in only {len(obs.frames)}"
            raise InputError(folder, f"camera {images.name}: {what} (frames with >= {options.min_corners} corners "
                             f"off one line; at least {MIN_FRAMES} needed, {len(obs.skipped)} frames skipped)")

    intrinsics, board_poses = {}, {}
    for name in names:
        try:
            K, dist, _, poses = calibrate_intrinsics(observations[name], options.board, options.distortion)
        except cv2.error as err:  # degenerate views that slipped through the checks above
            raise InputError(root / name, f"camera {name}: OpenCV could not calibrate it "
                             f"({str(err).strip().splitlines()[-1]})") from None
        intrinsics[name] = np.concatenate([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], dist])
        board_poses[name] = dict(zip(observations[name].frames, poses))
    frames_of = {n: list(observations[n].frames) for n in names}
    try:
        cam_from_ref = initial_extrinsics(names, reference, frames_of, board_poses)
    except InputError as err:
        raise InputError(root, err.problem) from None

    frame_names = sorted(set().union(*frames_of.values()))
    world_from_board = []
    for frame in frame_names:
        seen = [n for n in names if frame in board_poses[n]]
        best = max(seen, key=lambda n: len(observations[n].detections[observations[n].frames.index(frame)]))
        world_from_board.append(_inverse(cam_from_ref[best]) @ board_poses[best][frame])
    world_from_board = np.stack(world_from_board)

    frame_slot = {f: i for i, f in enumerate(frame_names)}
    corners = options.board.corners
    cam_index, frame_index, points, pixels = [], [], [], []
    for c, name in enumerate(names):
        obs = observations[name]
        for frame, detection in zip(obs.frames, obs.detections):
            cam_index.append(np.full(len(detection), c))
            frame_index.append(np.full(len(detection), frame_slot[frame]))
            points.append(corners[detection.ids])
            pixels.append(detection.pixels)
    problem = _Problem(names, reference, frame_names, _dist_free(options.distortion), np.concatenate(cam_index),
                       np.concatenate(frame_index), np.concatenate(points), np.concatenate(pixels))
    x0 = problem.pack(intrinsics, cam_from_ref, world_from_board)
    # ftol 1e-6: stopping there leaves the parameters within ~0.01 px of where tighter
    # tolerances creep to (along the flat focal/distortion valley, for hundreds of
    # evaluations), far below their statistical uncertainty.
    solution = least_squares(problem.residuals, x0, jac_sparsity=problem.sparsity(), method="trf", x_scale="jac",
                             loss="huber", f_scale=options.huber_px, ftol=1e-6, xtol=1e-9, max_nfev=200)
    x = solution.x
    residuals = problem.residuals(x).reshape(-1, 2)

    table = problem.intrinsics(x)
    cams, boards = problem.poses(x)
    rig_cameras = []
    for c, name in enumerate(names):
        fx, fy, cx, cy = table[c, :4]
        pose = cams[problem.pose_slot[name]] if name != reference else np.zeros(6)
        T = _pose(pose[:3], pose[3:])
        width, height = observations[name].image_size
        rig_cameras.append(Camera(name=name, width=width, height=height,
                                  K=np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), dist=table[c, 4:],
                                  R=T[:3, :3], t=T[:3, 3]))
    per_camera = {name: residuals[problem.cam_index == c] for c, name in enumerate(names)}
    return Calibration(rig=Rig(tuple(rig_cameras)), reference=reference, board=options.board,
                       frames=tuple(frame_names), world_from_board=np.stack([_pose(b[:3], b[3:]) for b in boards]),
                       observations=observations, residuals=per_camera,
                       rms_px=float(np.sqrt(np.mean(np.sum(residuals ** 2, axis=1)))), options=options)
