"""COLMAP boundary (pycolmap adapter): the only module that imports pycolmap and the only
place COLMAP's pixel convention appears.

COLMAP puts the centre of the top-left pixel at (0.5, 0.5); mvtex (OpenCV) at (0, 0).
On export cx, cy and every 2-D observation get +0.5; on import they get -0.5.
Cameras are PINHOLE (fx, fy, cx, cy); one image per camera named `<camera>.png`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from mvtex.data.camera import Camera
from mvtex.data.rig import Rig
from mvtex.util.checks import check_shape
from mvtex.util.errors import InputError, OutputError
from mvtex.util.output import atomic_path

COLMAP_PIXEL_OFFSET = 0.5


def _pycolmap():
    try:
        import pycolmap  # noqa: PLC0415 (loaded on use)
    except ImportError as err:  # a failed native import
        raise RuntimeError(f"pycolmap is needed for COLMAP models ({err}); pip install pycolmap") from err
    return pycolmap


def to_colmap_camera(camera: Camera, camera_id: int):
    """A PINHOLE pycolmap.Camera (principal point shifted by +0.5)."""
    pycolmap = _pycolmap()
    K = camera.K
    if abs(K[0, 1]) > 1e-12:
        raise ValueError(f"camera {camera.name!r}: skewed intrinsics cannot be written as COLMAP PINHOLE")
    camera.require_pinhole()
    return pycolmap.Camera(model="PINHOLE", width=camera.width, height=camera.height, camera_id=camera_id,
                           params=[K[0, 0], K[1, 1], K[0, 2] + COLMAP_PIXEL_OFFSET, K[1, 2] + COLMAP_PIXEL_OFFSET])


def rig_reconstruction(rig: Rig, observations: dict[str, np.ndarray] | None = None):
    """A pycolmap.Reconstruction with one camera and one image (`<name>.png`) per rig camera.

    Args:
        observations: optional camera name -> (k,2) OpenCV pixel observations, stored as the
            image's points2D (+0.5) in that order.

    Returns:
        (reconstruction, image_ids) with image_ids[name] the COLMAP image id.
    """
    pycolmap = _pycolmap()
    rec = pycolmap.Reconstruction()
    image_ids = {}
    for i, cam in enumerate(rig, start=1):
        rec.add_camera_with_trivial_rig(to_colmap_camera(cam, i))
        image = pycolmap.Image(name=f"{cam.name}.png", camera_id=i, image_id=i)
        if observations is not None and cam.name in observations:
            pts = np.asarray(observations[cam.name], dtype=np.float64).reshape(-1, 2) + COLMAP_PIXEL_OFFSET
            image.points2D = pycolmap.Point2DList([pycolmap.Point2D(p) for p in pts])
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(cam.R), cam.t))
        image_ids[cam.name] = i
    return rec, image_ids


def write_rig(rig: Rig, path: str | os.PathLike, text: bool = False) -> Path:
    """Export a rig as a COLMAP model (cameras, images, empty points3D) into directory `path`."""
    return write_model(rig_reconstruction(rig)[0], path, text=text)


def read_rig(path: str | os.PathLike) -> Rig:
    """Import a rig from a COLMAP model directory (binary or text): PINHOLE or SIMPLE_PINHOLE
    cameras with no distortion; each image becomes a camera named after its file stem."""
    path = Path(path)
    rec = read_model(path)
    cameras = []
    for image_id in sorted(rec.images):
        image = rec.images[image_id]
        cc = rec.cameras[image.camera_id]
        model = str(cc.model.name if hasattr(cc.model, "name") else cc.model)
        p = np.asarray(cc.params, dtype=np.float64)
        if model == "PINHOLE":
            fx, fy, cx, cy = p
        elif model == "SIMPLE_PINHOLE":
            fx = fy = p[0]
            cx, cy = p[1:]
        else:
            raise InputError(path, f"camera {image.camera_id}: model {model} not supported (use PINHOLE on undistorted images)")
        pose = image.cam_from_world()
        quat = np.asarray(pose.rotation.quat, dtype=np.float64)
        if not (np.all(np.isfinite(quat)) and np.linalg.norm(quat) > 1e-6
                and np.all(np.isfinite(np.asarray(pose.translation, dtype=np.float64)))):
            # pycolmap reads a zero quaternion as the identity: that is no rotation to import.
            raise InputError(path, f"image {image.name!r}: its pose (quaternion {quat.tolist()}, translation "
                             f"{np.asarray(pose.translation).tolist()}) is not a rigid transform")
        K = np.array([[fx, 0, cx - COLMAP_PIXEL_OFFSET], [0, fy, cy - COLMAP_PIXEL_OFFSET], [0, 0, 1]])
        try:  # names, sizes and intrinsics are checked by Camera like a rig YAML's
            cameras.append(Camera(name=Path(image.name).stem, width=cc.width, height=cc.height, K=K,
                                  R=np.asarray(pose.rotation.matrix()), t=np.asarray(pose.translation)))
        except ValueError as err:
            raise InputError(path, f"image {image.name!r}: {err}") from None
    if not cameras:
        raise InputError(path, "COLMAP model has no images")
    try:
        return Rig(tuple(cameras))
    except ValueError as err:
        raise InputError(path, str(err)) from None


def point_reconstruction(rig: Rig, observations: dict[str, np.ndarray], points: np.ndarray,
                         tracks: dict[str, np.ndarray], colors: np.ndarray | None = None):
    """A pycolmap.Reconstruction with the rig's images, 2-D observations and 3-D points.

    Args:
        rig: the cameras; one COLMAP camera and image (`<name>.png`) each.
        observations: camera name -> (k_c,2) OpenCV pixel observations (points2D, +0.5 on export).
        points: (t,3) world positions of the 3-D points.
        tracks: camera name -> (t,) int: index into observations[name] of point j's
            observation in that camera, -1 where it has none.
        colors: optional (t,3) uint8 RGB per point.

    Returns:
        (reconstruction, point3D_ids) with point3D_ids (t,) int64 the COLMAP ids of `points`.
        Reprojection errors are computed (`update_point_3d_errors`).
    """
    pycolmap = _pycolmap()
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    colors = np.zeros((len(points), 3), np.uint8) if colors is None else np.asarray(colors, np.uint8)
    rec, image_ids = rig_reconstruction(rig, observations)
    names = [name for name in rig.names if name in tracks]
    table = np.stack([np.asarray(tracks[name], dtype=np.int64) for name in names], axis=1) if names else \
        np.full((len(points), 0), -1)
    if table.shape[0] != len(points):
        raise ValueError(f"tracks have {table.shape[0]} entries, points {len(points)}")
    ids = np.empty(len(points), dtype=np.int64)
    for j, (xyz, row) in enumerate(zip(points, table)):
        elements = [pycolmap.TrackElement(image_ids[names[c]], int(row[c])) for c in np.flatnonzero(row >= 0)]
        ids[j] = rec.add_point3D(xyz, pycolmap.Track(elements), colors[j])
    rec.update_point_3d_errors()
    return rec, ids


def _counts(reconstruction) -> tuple[int, int, int, int]:
    return (reconstruction.num_cameras(), reconstruction.num_images(), reconstruction.num_points3D(),
            reconstruction.compute_num_observations())


def write_model(reconstruction, path: str | os.PathLike, text: bool = False) -> Path:
    """Write a pycolmap.Reconstruction (binary by default) into directory `path`, atomically.

    COLMAP's writers do not report a failed write (a full disk, a file-size limit: the
    files are cut short): the model is read back before it is renamed into place and must
    hold what was written.

    Raises:
        OutputError: naming `path`, when the written model does not read back whole.
    """

    pycolmap = _pycolmap()
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.mkdir()
        (reconstruction.write_text if text else reconstruction.write_binary)(str(tmp))
        try:
            back = _counts(pycolmap.Reconstruction(str(tmp)))
        except Exception as err:  # pycolmap raises generic errors for unreadable models
            back = f"unreadable ({str(err).strip().splitlines()[-1] if str(err).strip() else type(err).__name__})"
        if back != _counts(reconstruction):
            raise OutputError(path, "cannot write it (COLMAP's writer stopped short: the written model reads back "
                              f"{back if isinstance(back, str) else 'with fewer entries'}; is the disk full?)")
    return path


def read_model(path: str | os.PathLike):
    """Read a COLMAP model directory (binary or text) as a pycolmap.Reconstruction.

    Raises:
        InputError: the directory is missing or not a readable model.
    """
    pycolmap = _pycolmap()
    path = Path(path)
    if not path.is_dir():
        raise InputError(path, "COLMAP model directory not found")
    try:
        return pycolmap.Reconstruction(str(path))
    except Exception as err:  # pycolmap raises generic errors for unreadable models
        raise InputError(path, f"cannot read COLMAP model ({err})") from None


def model_summary(path: str | os.PathLike) -> dict:
    """Read a COLMAP model directory back and summarise it.

    Returns:
        dict with num_cameras, num_images, num_points3D, num_observations,
        mean_track_length and mean_reprojection_error_px (COLMAP's own computation:
        the mean over 3-D points of each point's mean reprojection error).
    """
    rec = read_model(path)
    rec.update_point_3d_errors()
    return {"num_cameras": rec.num_cameras(), "num_images": rec.num_images(), "num_points3D": rec.num_points3D(),
            "num_observations": rec.compute_num_observations(),
            "mean_track_length": float(rec.compute_mean_track_length()) if rec.num_points3D() else 0.0,
            "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error())}


def triangulate_colmap(cameras: Sequence[Camera], pixels: np.ndarray, max_error_px: float = 4.0) -> np.ndarray | None:
    """COLMAP's robust multi-view triangulation of one point (LO-RANSAC + refinement).

    Args:
        cameras: the m ≥ 2 observing cameras.
        pixels: (m,2) OpenCV pixel observations (the +0.5 is added here).
        max_error_px: RANSAC inlier threshold on the reprojection error.

    Returns:
        (3,) float64 world point, or None where COLMAP finds no consistent point.
    """
    pycolmap = _pycolmap()
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2) + COLMAP_PIXEL_OFFSET
    options = pycolmap.EstimateTriangulationOptions()
    options.residual_type = pycolmap.TriangulationResidualType.REPROJECTION_ERROR
    options.ransac.max_error = float(max_error_px)
    options.ransac.random_seed = 0
    result = pycolmap.estimate_triangulation(
        pixels, [pycolmap.Rigid3d(pycolmap.Rotation3d(c.R), c.t) for c in cameras],
        [to_colmap_camera(c, i + 1) for i, c in enumerate(cameras)], options)
    if result is None:
        return None
    return np.asarray(result["xyz"], dtype=np.float64).reshape(3)


def track_tables(names: Sequence[str], pixels: np.ndarray, observed: np.ndarray
                 ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Per-point observations (N,C,2) as the per-image lists `point_reconstruction` takes.

    Args:
        names: the C camera names.
        pixels: (N,C,2) OpenCV pixels; observed: (N,C) bool.

    Returns:
        observations: name -> (k_c,2) the pixels camera c observes, in point order;
        tracks: name -> (N,) int index into observations[name], -1 where unobserved.
    """
    observations, tracks = {}, {}
    for c, name in enumerate(names):
        seen = np.flatnonzero(observed[:, c])
        observations[name] = np.asarray(pixels[seen, c], dtype=np.float64)
        track = np.full(len(observed), -1, dtype=np.int64)
        track[seen] = np.arange(len(seen))
        tracks[name] = track
    return observations, tracks


def _bearing_vectors(camera: Camera, pixels: np.ndarray) -> np.ndarray:
    """Unit camera-frame rays (k,3) through OpenCV pixels (k,2)."""
    rays = np.concatenate([pixels, np.ones((len(pixels), 1))], axis=1) @ np.linalg.inv(camera.K).T
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def triangulate_tracks(cameras: Sequence[Camera], pixels: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Triangulate tracks with COLMAP: multi-view triangulation, then a points-only bundle
    adjustment with every camera pose and intrinsic held constant.

    The initial point of each track is `pycolmap.triangulate_multi_view_point` on the
    track's bearing vectors; Ceres then minimises the summed squared reprojection error
    (trivial loss) of all points at once, which for fixed cameras is each point's own
    least-squares problem, the one `mvtex.recon.geometry.refine_points` solves.

    Args:
        cameras: the C cameras (PINHOLE: no skew, no distortion).
        pixels: (N,C,2) OpenCV pixel observations.
        weights: (N,C): > 0 where camera c observes point n (≥ 2 per point); values other
            than 0/1 do not weight the residuals.

    Returns:
        (N,3) float64 points (NaN where the linear triangulation is degenerate).
    """
    pycolmap = _pycolmap()
    sizes = check_shape(pixels, "pixels", ("N", len(cameras), 2))
    check_shape(weights, "weights", ("N", len(cameras)), sizes)
    pixels = np.asarray(pixels, dtype=np.float64)
    observed = np.asarray(weights) > 0
    out = np.full((len(pixels), 3), np.nan)
    if not len(pixels):
        return out
    if np.any(observed.sum(axis=1) < 2):
        raise ValueError("every track needs ≥ 2 observations (weights > 0)")
    cams_from_world = [np.concatenate([c.R, c.t[:, None]], axis=1) for c in cameras]
    rays = [_bearing_vectors(c, np.nan_to_num(pixels[:, k])) for k, c in enumerate(cameras)]
    for j in range(len(pixels)):
        used = np.flatnonzero(observed[j])
        xyz = pycolmap.triangulate_multi_view_point([cams_from_world[k] for k in used],
                                                    np.stack([rays[k][j] for k in used]))
        if xyz is not None:
            out[j] = np.asarray(xyz, dtype=np.float64).reshape(3)
    good = np.flatnonzero(np.all(np.isfinite(out), axis=1))
    if not len(good):
        return out
    rig = Rig(tuple(cameras))
    observations, tracks = track_tables(rig.names, pixels[good], observed[good])
    model, point_ids = point_reconstruction(rig, observations, out[good], tracks)
    _adjust_points_only(model)
    out[good] = np.stack([model.points3D[int(i)].xyz for i in point_ids])
    return out


def _adjust_points_only(model) -> None:
    """Ceres bundle adjustment of a model's 3-D points; poses and intrinsics constant."""
    pycolmap = _pycolmap()
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = options.refine_principal_point = options.refine_extra_params = False
    options.refine_rig_from_world = options.refine_sensor_from_rig = False
    options.print_summary = False
    solver = options.ceres.solver_options
    # Converge to the optimum, not to Ceres' default gradient tolerance (1e-4 px² / m).
    solver.function_tolerance = 0.0
    solver.gradient_tolerance = 1e-12
    solver.parameter_tolerance = 1e-14
    solver.num_threads = 1
    config = pycolmap.BundleAdjustmentConfig()
    for image_id, image in model.images.items():
        config.add_image(image_id)
        config.set_constant_cam_intrinsics(image.camera_id)
        config.set_constant_rig_from_world_pose(image.frame_id)
    summary = pycolmap.create_default_bundle_adjuster(options, config, model).solve()
    if summary.termination_type == pycolmap.BundleAdjustmentTerminationType.FAILURE:
        raise RuntimeError(f"COLMAP bundle adjustment failed: {summary.summary()}")
