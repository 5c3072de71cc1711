"""The built-in datasets (DESIGN §8): a T-shirt on a mannequin (`mvtex.synth.shirt`) or a
flared skirt on hips and legs (`mvtex.synth.skirt`), chosen by `SynthOptions.garment`; the
wearer is the dataset's body (body.npz + body.npy, DESIGN §4) unless `SynthOptions.body`
is off.

A ground-truth pose is a smooth deformation of the rest garment that its body shares
(bend, side bend, twist, shrug and arm lift for the shirt; hem swing and hip tilt for the
skirt) and folds made the way cloth makes them (material slides towards a forming fold
along a unit-speed cross-section), so edge lengths stay close to rest.

The *inferred* meshes come from a predictor fitted on the training poses (PCA of the
ground-truth shapes, of at most `MAX_BASIS_SHAPES` evenly spaced ones; ridge regression
from the pose to the PCA coefficients over all of them). They may cut into the body, as
real predictors' meshes do; the ground truth keeps clear of it (the statistics measure both).
`synthesize` writes nothing; `mvtex.data.dataset.save_dataset` owns the file format, and
`write_synth` writes the same files while streaming the shapes to disk.
"""

from __future__ import annotations

import json
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from tqdm import tqdm

from mvtex.data.dataset import default_split, metadata, validate_mesh
from mvtex.data.mesh import edge_strain, edges
from mvtex.synth import shirt, skirt
from mvtex.synth.distance import SurfaceDistance
from mvtex.synth.options import SynthOptions
from mvtex.synth.predictor import _CHUNK, fit_predictor
from mvtex.util.checks import as_path, check_instance
from mvtex.util.files import create_npy
from mvtex.util.output import atomic_path, writer


@dataclass(frozen=True)
class _Garment:
    """A built-in garment: its rest mesh, its shape per pose, and its body."""

    faces: np.ndarray
    uv: np.ndarray
    rest: np.ndarray
    pose_dim: int
    sample_poses: Callable[[int, int], np.ndarray]
    shape: Callable  # pose -> (positions (n,3) in vertex order, fold info [(depth, wavelength, peak angle)])
    body_faces: np.ndarray
    body_rest: np.ndarray
    pose_body: Callable  # pose -> (nb,3) float32


def _garment(garment: str) -> _Garment:
    if garment == "shirt":

        faces, uv, rest = shirt.make_garment()
        material = shirt._Material(rest, uv)

        def shape(pose):
            positions, info = shirt._deform_material(material, pose)
            return positions[material.inverse], info

        body_faces, body_rest = shirt.make_body()
        return _Garment(faces, uv, rest, shirt.POSE_DIM, shirt.sample_poses, shape, body_faces, body_rest,
                        shirt.pose_body)

    body_faces, body_rest = skirt.make_body()
    return _Garment(*skirt.make_garment(), skirt.POSE_DIM, skirt.sample_poses, skirt.deform_with_info, body_faces,
                    body_rest, skirt.pose_body)


class _Rows:
    """The rows `index` of a (K, n, 3) array or `_RowFile`, read only when indexed: the
    predictor fit reads the training shapes block by block through it."""

    def __init__(self, base, index: np.ndarray):
        self.base, self.index = base, index
        self.shape = (len(index), *base.shape[1:])

    def __getitem__(self, key) -> np.ndarray:
        return np.asarray(self.base[self.index[key]])


def _generate(options: SynthOptions, gt_out, inferred_out, body_out, progress: bool = False) -> tuple:
    """Fill gt_out, inferred_out ((K, n, 3) float32) and body_out ((K, nb, 3) float32, or
    None without a body), in memory or `_RowFile`, pose by pose and block by block, and
    compute the statistics. The shapes are computed per pose (or per row of a block), so
    they do not depend on the block size; the statistics' means are sums of per-pose sums
    (equal to a one-pass mean up to rounding).

    With `progress`, a bar on stderr counts the gt shapes, then the inferred ones.

    Returns:
        (garment, poses, split, stats) as in `synthesize`.
    """

    bar = tqdm(total=2 * options.num_poses, desc=f"synth {options.garment}", unit="shape", disable=not progress,
               file=sys.stderr)
    garment = _garment(options.garment)
    poses = garment.sample_poses(options.num_poses, options.seed)
    _, first = np.unique(garment.rest, axis=0, return_index=True)  # one vertex per distinct point
    distance = None
    if body_out is not None:

        distance = SurfaceDistance(garment.rest[first], garment.body_rest, garment.body_faces)
    depths, wavelengths, peaks, clearance = [], [], [], []
    for k, pose in enumerate(poses):
        positions, info = garment.shape(pose)
        stored = positions.astype(np.float32)
        gt_out[k] = stored
        if body_out is not None:
            body = garment.pose_body(pose)
            body_out[k] = body
            clearance.append(float(distance(stored[first], body).min()))
        depths.append(max(d for d, _, _ in info))
        wavelengths += [w for d, w, _ in info if d >= 5e-3]
        peaks.append(max(p for _, _, p in info))
        bar.update(1)
    split = default_split(options.num_poses, options.seed)
    train = np.asarray(split["train"], dtype=np.int64)
    predictor = fit_predictor(_Rows(gt_out, train), poses[train], options.pca_components, options.ridge)
    edge_list = edges(garment.faces)
    # Per-pose sums (K,) float64: the means over poses and edges / vertices need no (K, e)
    # array, so memory does not grow with K.
    strain_gt = np.empty(options.num_poses)
    strain_inferred = np.empty(options.num_poses)
    squared = np.empty(options.num_poses)
    inside = np.zeros(options.num_poses)
    deepest = np.zeros(options.num_poses)
    for lo in range(0, options.num_poses, _CHUNK):
        block = slice(lo, min(lo + _CHUNK, options.num_poses))
        inferred = predictor.predict(poses[block])
        inferred_out[block] = inferred
        gt = np.asarray(gt_out[block])
        strain_gt[block] = np.abs(edge_strain(gt, garment.rest, edge_list)).sum(axis=1)
        strain_inferred[block] = np.abs(edge_strain(inferred, garment.rest, edge_list)).sum(axis=1)
        # Row by row: a sum over a block's rows could group the additions by the block's shape.
        squared[block] = [np.sum((i.astype(np.float64) - g.astype(np.float64)) ** 2) for i, g in zip(inferred, gt)]
        if body_out is not None:
            bodies = np.asarray(body_out[block])
            for row, k in enumerate(range(block.start, block.stop)):
                signed = distance(inferred[row][first], bodies[row])
                inside[k], deepest[k] = np.mean(signed < 0.0), max(0.0, -float(signed.min()))
        bar.update(block.stop - block.start)

    def rmse(part: list[int]) -> float:
        # As `mesh.rms_distance` over the poses of one split.
        return float(np.sqrt(squared[part].sum() / (len(part) * len(garment.rest))))

    stats = {
        "num_vertices": float(len(garment.rest)),
        "num_faces": float(len(garment.faces)),
        "pose_dim": float(garment.pose_dim),
        "fold_depth_m": float(np.median(depths)),
        "fold_wavelength_m": float(np.median(wavelengths)) if wavelengths else 0.0,
        "max_fold_angle_deg": float(np.degrees(max(peaks))),
        "overhanging_pose_fraction": float(np.mean(np.array(peaks) > np.pi / 2)),
        "mean_abs_edge_strain_gt": float(strain_gt.sum() / strain_gt.size / len(edge_list)),
        "mean_abs_edge_strain_inferred": float(strain_inferred.sum() / strain_inferred.size / len(edge_list)),
        "rmse_inferred_train_m": rmse(split["train"]),
        "rmse_inferred_test_m": rmse(split["test"]),
    }
    if body_out is not None:
        stats.update({
            "body_num_vertices": float(len(garment.body_rest)),
            "body_num_faces": float(len(garment.body_faces)),
            "clearance_m": float(min(clearance)),
            "inferred_inside_body_fraction": float(inside.mean()),
            "inferred_inside_body_depth_m": float(deepest.max()),
        })
    bar.close()
    return garment, poses, split, stats


@dataclass(frozen=True)
class SynthResult:
    """What `write_synth` wrote (`mvtex synth --json` is `to_json()`: the statistics).

    Attributes:
        path: the dataset directory; options: the `SynthOptions` it was made with.
        stats: the dataset's statistics, as stored under "stats" in dataset.json (vertex and
            face counts, fold depth and wavelength, strain, the predictor's error, and with a
            body its size and the cloth's clearance from it).
    """

    path: str
    options: SynthOptions
    stats: dict

    def to_json(self) -> dict:
        return dict(self.stats)


def synthesize(options: SynthOptions = SynthOptions()) -> dict:
    """Generate the built-in dataset in memory (nothing is written).

    Returns:
        dict with name (the garment: "shirt" or "skirt"), faces (m, 3) int32, uv (n, 2)
        float32, rest (n, 3) float32, gt and inferred (K, n, 3) float32, poses (K, P)
        float32, split {"train", "val", "test": sorted lists of pose indices} (80/10/10,
        seeded), body_faces (mb, 3) int32 and body (K, nb, 3) float32 (both None with
        `options.body` off), and stats, a dict of floats: num_vertices, num_faces,
        pose_dim; fold_depth_m (median over poses of the deepest fold's peak-to-trough
        normal offset); fold_wavelength_m (median over folds deeper than 5 mm);
        max_fold_angle_deg and overhanging_pose_fraction (poses whose steepest fold passes
        90 degrees); mean_abs_edge_strain_gt / _inferred (mean |length / rest length - 1|
        over poses and edges); rmse_inferred_train_m / _test_m (per-vertex RMSE vs gt on
        that split); with a body also body_num_vertices, body_num_faces, clearance_m (the
        least signed distance of a gt vertex to the body mesh over all poses),
        inferred_inside_body_fraction (mean over poses of the fraction of inferred vertices
        inside the body) and inferred_inside_body_depth_m (the deepest of them).

    """

    check_instance(options, SynthOptions, "options")
    garment = _garment(options.garment)
    shape = (options.num_poses, len(garment.rest), 3)
    gt, inferred = np.empty(shape, dtype=np.float32), np.empty(shape, dtype=np.float32)
    body = np.empty((options.num_poses, len(garment.body_rest), 3), np.float32) if options.body else None
    garment, poses, split, stats = _generate(options, gt, inferred, body)
    return dict(name=options.garment, faces=garment.faces, uv=garment.uv, rest=garment.rest, gt=gt, inferred=inferred,
                poses=poses, split=split, stats=stats, body_faces=garment.body_faces if options.body else None,
                body=body)


class _RowFile:
    """A (K, n, 3) float32 .npy file written and read in blocks of rows through short-lived
    memory maps: the process never keeps more than one block mapped, so its resident memory
    does not grow with K. Supports `obj[k] = rows`, `obj[block] = rows` and `obj[index]`."""

    def __init__(self, path, shape: tuple[int, ...]):

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


@writer("synth", out="path")
def write_synth(path: str | os.PathLike, options: SynthOptions = SynthOptions(), *, progress: bool = False,
                overwrite: bool = False) -> SynthResult:
    """Synthesize and save the dataset directory at `path` (format: DESIGN §4) atomically,
    streaming: the shapes (and the body) go to gt.npy / inferred.npy / body.npy block by
    block as they are made, so memory does not hold all poses, and the predictor fit reads
    the training shapes in blocks too (`fit_predictor`): peak memory does not grow with
    `num_poses`. The files are byte for byte those `mvtex.data.dataset.save_dataset` writes
    for `synthesize(options)` (tests/synth/test_synth.py checks it). With `progress`, a bar
    on stderr counts the shapes made.

    The statistics are also stored under "stats" in dataset.json, the garment under
    "garment".

    Args:
        progress: a progress bar on stderr (each pose counted twice: its shapes, then its
            inferred shape).

    Returns:
        A `SynthResult`; its `stats` are those of `synthesize`.
    """

    path = as_path(path, "path")
    check_instance(options, SynthOptions, "options")

    path = Path(path)
    garment = _garment(options.garment)
    validate_mesh(garment.faces, garment.uv, path)
    shape = (options.num_poses, len(garment.rest), 3)
    with atomic_path(path) as tmp:
        tmp.mkdir()
        gt, inferred = _RowFile(tmp / "gt.npy", shape), _RowFile(tmp / "inferred.npy", shape)
        body = _RowFile(tmp / "body.npy", (options.num_poses, len(garment.body_rest), 3)) if options.body else None
        garment, poses, split, stats = _generate(options, gt, inferred, body, progress=progress)
        body_faces = np.asarray(garment.body_faces, np.int32) if options.body else None
        meta = metadata(options.garment, shape[0], shape[1], poses.shape[1], body_faces, body,
                        garment=options.garment, stats=stats)
        np.savez_compressed(tmp / "mesh.npz", faces=np.asarray(garment.faces, np.int32),
                            uv=np.asarray(garment.uv, np.float32), rest=np.asarray(garment.rest, np.float32))
        np.save(tmp / "poses.npy", np.asarray(poses, np.float32), allow_pickle=False)
        if options.body:
            np.savez_compressed(tmp / "body.npz", faces=body_faces)
        parts = {k: [int(i) for i in split[k]] for k in ("train", "val", "test")}
        (tmp / "split.json").write_text(json.dumps(parts) + "\n")
        (tmp / "dataset.json").write_text(json.dumps(meta, indent=2) + "\n")
    return SynthResult(path=str(path), options=options, stats=stats)
