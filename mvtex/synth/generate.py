"""The built-in datasets: a shirt-like garment with pose-driven folds (DESIGN §8), and a
flared skirt whose hem falls into flutes (`mvtex.synth.skirt`), chosen by `SynthOptions.garment`.

The garment is a closed torso tube, open at collar and waist, in meters with y up and
its front facing +z. Its material is described by *material coordinates* (a, h): a is
the arc length around the rest cross-section (0 at the front centre, growing towards +x
there) and h the rest height. Because the rest tube is a cylinder, the (a, h) plane
unrolls onto it without distortion, and the two UV charts (front and back panel) are
just that plane scaled by one factor.

A ground-truth pose is built in two layers:

* a smooth *base* map (a, h) -> 3-D: the tube bent forward/back and sideways, twisted
  and with its shoulders lifted, like a rod whose cross-sections follow a rotating frame;
* *folds* made the way cloth makes them: along the fold normal s the tangent angle
  follows phi(s) = phi_max * env(s) * sin(2 pi s / wavelength), and integrating
  (cos phi, sin phi) gives a unit-speed profile, so edge lengths stay close to rest.
  Its in-plane part slides the material towards the fold, its out-of-plane part is an
  offset along the base surface's normal.

The *inferred* meshes come from a predictor fitted on the training poses (PCA of the
ground-truth shapes, of at most `MAX_BASIS_SHAPES` evenly spaced ones; ridge regression
from the pose to the PCA coefficients over all of them).
`synthesize` writes nothing; `mvtex.data.dataset.save_dataset` owns the file format, and
`write_synth` writes the same files while streaming the shapes to disk.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from mvtex.data.dataset import default_split
from mvtex.data.mesh import edge_strain, edges
from mvtex.synth.predictor import _CHUNK, fit_predictor
from mvtex.synth.shirt import POSE_DIM, _deform_material, _material_coords, make_garment, sample_poses

GARMENTS = ("shirt", "skirt")






@dataclass(frozen=True)
class SynthOptions:
    """Options of `synthesize`.

    Attributes:
        num_poses: number of poses K (at least 3, one per split).
        seed: seeds the poses and the 80/10/10 split.
        pca_components: PCA components of the predictor (its capacity).
        ridge: ridge penalty of the pose -> PCA-coefficient regression (bias unpenalized).
        garment: "shirt" (a torso tube with bend, twist and side folds) or "skirt" (a
            flared cone whose hem swings and falls into flutes, `mvtex.synth.skirt`).
    """

    num_poses: int = 300
    seed: int = 0
    pca_components: int = 6
    ridge: float = 1e-2
    garment: str = "shirt"


def _garment_shape_function(garment: str):
    """((faces, uv, rest), shape) of a built-in garment, where shape(pose) -> (positions
    (n,3) in vertex order, fold info [(depth, wavelength, peak angle), ...])."""
    if garment == "shirt":
        faces, uv, rest = make_garment()
        a, h, inverse = _material_coords(rest, uv)

        def shape(pose):
            positions, info = _deform_material(a, h, pose)
            return positions[inverse], info

        return (faces, uv, rest), shape
    from mvtex.synth import skirt

    return skirt.make_garment(), skirt.deform_with_info


def _check_options(options: SynthOptions) -> None:
    if options.garment not in GARMENTS:
        raise ValueError(f"garment must be one of {', '.join(GARMENTS)}, got {options.garment!r}")
    if options.num_poses < 3:
        raise ValueError(f"num_poses must be at least 3 (one pose per split), got {options.num_poses}")
    if options.pca_components < 1 or options.ridge < 0:
        raise ValueError(f"need pca_components >= 1 and ridge >= 0, got {options.pca_components} and {options.ridge}")


class _Rows:
    """The rows `index` of a (K, n, 3) array or `_RowFile`, read only when indexed: the
    predictor fit reads the training shapes block by block through it."""

    def __init__(self, base, index: np.ndarray):
        self.base, self.index = base, index
        self.shape = (len(index), *base.shape[1:])

    def __getitem__(self, key) -> np.ndarray:
        return np.asarray(self.base[self.index[key]])


def _generate(options: SynthOptions, gt_out: np.ndarray, inferred_out: np.ndarray) -> tuple:
    """Fill gt_out and inferred_out ((K, n, 3) float32, in memory or `_RowFile`) pose by
    pose and block by block, and compute the statistics. The shapes are computed per pose
    (or per row of a block), so they do not depend on the block size; the statistics'
    means are sums of per-pose sums (equal to a one-pass mean up to rounding).

    Returns:
        (faces, uv, rest, poses, split, stats) as in `synthesize`.
    """
    (faces, uv, rest), shape = _garment_shape_function(options.garment)
    poses = sample_poses(options.num_poses, options.seed)
    depths, wavelengths, peaks = [], [], []
    for k, pose in enumerate(poses):
        positions, info = shape(pose)
        gt_out[k] = positions
        depths.append(max(d for d, _, _ in info))
        wavelengths += [w for d, w, _ in info if d >= 5e-3]
        peaks.append(max(p for _, _, p in info))
    split = default_split(options.num_poses, options.seed)
    train = np.asarray(split["train"], dtype=np.int64)
    predictor = fit_predictor(_Rows(gt_out, train), poses[train], options.pca_components, options.ridge)
    edge_list = edges(faces)
    # Per-pose sums (K,) float64: the means over poses and edges / vertices need no (K, e)
    # array, so memory does not grow with K.
    strain_gt = np.empty(options.num_poses)
    strain_inferred = np.empty(options.num_poses)
    squared = np.empty(options.num_poses)
    for lo in range(0, options.num_poses, _CHUNK):
        block = slice(lo, min(lo + _CHUNK, options.num_poses))
        inferred = predictor.predict(poses[block])
        inferred_out[block] = inferred
        gt = np.asarray(gt_out[block])
        strain_gt[block] = np.abs(edge_strain(gt, rest, edge_list)).sum(axis=1)
        strain_inferred[block] = np.abs(edge_strain(inferred, rest, edge_list)).sum(axis=1)
        squared[block] = np.sum((inferred.astype(np.float64) - gt.astype(np.float64)) ** 2, axis=(1, 2))

    def rmse(part: list[int]) -> float:
        # As `mesh.rms_distance` over the poses of one split.
        return float(np.sqrt(squared[part].sum() / (len(part) * len(rest))))

    stats = {
        "num_vertices": float(len(rest)),
        "num_faces": float(len(faces)),
        "pose_dim": float(POSE_DIM),
        "fold_depth_m": float(np.median(depths)),
        "fold_wavelength_m": float(np.median(wavelengths)) if wavelengths else 0.0,
        "max_fold_angle_deg": float(np.degrees(max(peaks))),
        "overhanging_pose_fraction": float(np.mean(np.array(peaks) > np.pi / 2)),
        "mean_abs_edge_strain_gt": float(strain_gt.sum() / strain_gt.size / len(edge_list)),
        "mean_abs_edge_strain_inferred": float(strain_inferred.sum() / strain_inferred.size / len(edge_list)),
        "rmse_inferred_train_m": rmse(split["train"]),
        "rmse_inferred_test_m": rmse(split["test"]),
    }
    return faces, uv, rest, poses, split, stats


def synthesize(options: SynthOptions = SynthOptions()) -> dict:
    """Generate the built-in dataset in memory (nothing is written).

    Returns:
        dict with name (the garment: "shirt" or "skirt"), faces (m, 3) int32, uv (n, 2) float32, rest (n, 3) float32,
        gt and inferred (K, n, 3) float32, poses (K, POSE_DIM) float32, split
        {"train", "val", "test": sorted lists of pose indices} (80/10/10, seeded), and
        stats, a dict of floats: num_vertices, num_faces, pose_dim; fold_depth_m (median
        over poses of the deepest fold's peak-to-trough normal offset); fold_wavelength_m
        (median over folds deeper than 5 mm); max_fold_angle_deg and
        overhanging_pose_fraction (poses whose steepest fold passes 90 degrees);
        mean_abs_edge_strain_gt / _inferred (mean |length / rest length - 1| over poses
        and edges); rmse_inferred_train_m / _test_m (per-vertex RMSE vs gt on that split).

    Raises:
        ValueError: num_poses < 3, pca_components < 1, ridge < 0 or an unknown garment.
    """
    _check_options(options)
    n = len(_garment_shape_function(options.garment)[0][2])
    gt = np.empty((options.num_poses, n, 3), dtype=np.float32)
    inferred = np.empty_like(gt)
    faces, uv, rest, poses, split, stats = _generate(options, gt, inferred)
    return dict(name=options.garment, faces=faces, uv=uv, rest=rest, gt=gt, inferred=inferred, poses=poses,
                split=split, stats=stats)


class _RowFile:
    """A (K, n, 3) float32 .npy file written and read in blocks of rows through short-lived
    memory maps: the process never keeps more than one block mapped, so its resident memory
    does not grow with K. Supports `obj[k] = rows`, `obj[block] = rows` and `obj[index]`."""

    def __init__(self, path, shape: tuple[int, ...]):
        from mvtex.util.files import create_npy

        self.path = path
        self.shape = shape
        create_npy(path, np.float32, shape)

    def _map(self, mode: str) -> np.memmap:
        return np.load(self.path, mmap_mode=mode, allow_pickle=False)

    def __setitem__(self, index, rows) -> None:
        mapped = self._map("r+")
        mapped[index] = rows
        mapped.flush()
        del mapped

    def __getitem__(self, index) -> np.ndarray:
        mapped = self._map("r")
        out = np.array(mapped[index])
        del mapped
        return out


def write_synth(path: str | os.PathLike, options: SynthOptions = SynthOptions()) -> dict:
    """Synthesize and save the dataset directory at `path` (format: DESIGN §4) atomically,
    streaming: the shapes go to gt.npy / inferred.npy block by block as they are made, so
    memory does not hold all poses, and the predictor fit reads the training shapes in
    blocks too (`fit_predictor`): peak memory does not grow with `num_poses`.
    The files are byte for byte those `mvtex.data.dataset.save_dataset` writes for
    `synthesize(options)` (tests/test_synth.py checks it).

    The statistics are also stored under "stats" in dataset.json, the garment under
    "garment".

    Returns:
        The `stats` dict of `synthesize`.
    """
    import json
    from pathlib import Path

    from mvtex.data.dataset import FORMAT, VERSION, validate_mesh
    from mvtex.util.output import atomic_path

    _check_options(options)
    path = Path(path)
    (faces, uv, rest), _ = _garment_shape_function(options.garment)
    validate_mesh(faces, uv, path)
    shape = (options.num_poses, len(rest), 3)
    with atomic_path(path) as tmp:
        tmp.mkdir()
        gt, inferred = _RowFile(tmp / "gt.npy", shape), _RowFile(tmp / "inferred.npy", shape)
        faces, uv, rest, poses, split, stats = _generate(options, gt, inferred)
        meta = {"format": FORMAT, "version": VERSION, "name": options.garment, "units": "m", "num_poses": shape[0],
                "num_vertices": shape[1], "pose_dim": int(poses.shape[1]), "garment": options.garment, "stats": stats}
        np.savez_compressed(tmp / "mesh.npz", faces=np.asarray(faces, np.int32), uv=np.asarray(uv, np.float32),
                            rest=np.asarray(rest, np.float32))
        np.save(tmp / "poses.npy", np.asarray(poses, np.float32), allow_pickle=False)
        (tmp / "split.json").write_text(json.dumps({k: [int(i) for i in split[k]] for k in ("train", "val", "test")}) + "\n")
        (tmp / "dataset.json").write_text(json.dumps(meta, indent=2) + "\n")
    return stats
