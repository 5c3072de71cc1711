"""`mvtex import`: OBJ/PLY sequences with one connectivity -> an mvtex dataset.
"""

from __future__ import annotations

import glob as globlib
import os
from pathlib import Path

import numpy as np

from mvtex.data.dataset import save_dataset
from mvtex.util.errors import InputError
from mvtex.util.files import load_npy


def _sorted_glob(pattern: str, what: str) -> list[str]:
    files = sorted(globlib.glob(pattern))
    if not files:
        raise InputError(pattern, f"no {what} files match")
    return files


def _read_mesh(file: str):
    import trimesh

    try:
        mesh = trimesh.load(file, process=False, maintain_order=True, force="mesh")
    except Exception as err:  # trimesh raises many kinds for unreadable files
        raise InputError(file, f"cannot read mesh ({type(err).__name__}: {err})") from None
    if not hasattr(mesh, "faces") or len(mesh.faces) == 0:
        raise InputError(file, "no triangle faces")
    return mesh


def import_sequences(out: str | os.PathLike, gt_glob: str, inferred_glob: str,
                     poses_file: str | os.PathLike | None = None, name: str | None = None,
                     progress: bool = True) -> Path:
    """Turn two OBJ/PLY sequences with identical connectivity into a dataset.

    Files are paired in sorted order. The first gt mesh defines faces and uv (and `rest`);
    every other mesh must have the same vertex count and the same faces, or InputError.
    Without `poses_file` (.npy (K,P) or .txt/.csv rows), the pose vector is the frame index.
    """
    gt_files = _sorted_glob(gt_glob, "gt")
    inf_files = _sorted_glob(inferred_glob, "inferred")
    if len(gt_files) != len(inf_files):
        raise InputError(inferred_glob, f"{len(inf_files)} inferred meshes for {len(gt_files)} gt meshes")
    first = _read_mesh(gt_files[0])
    faces = np.asarray(first.faces, dtype=np.int32)
    n = len(first.vertices)
    uv = getattr(getattr(first, "visual", None), "uv", None)
    if uv is None or len(uv) != n:
        raise InputError(gt_files[0], "no per-vertex texture coordinates (need OBJ 'vt' or PLY texcoords)")
    uv = np.asarray(uv, dtype=np.float32)
    if not np.all(np.isfinite(uv)):
        raise InputError(gt_files[0], "NaN or infinite texture coordinates")
    gt = np.empty((len(gt_files), n, 3), dtype=np.float32)
    inferred = np.empty_like(gt)
    from tqdm import tqdm

    for k, (g, i) in enumerate(tqdm(list(zip(gt_files, inf_files)), desc="import", unit="pose", disable=not progress)):
        for file, target in ((g, gt), (i, inferred)):
            mesh = first if file == gt_files[0] else _read_mesh(file)
            if np.asarray(mesh.vertices).ndim != 2 or np.asarray(mesh.vertices).shape[1] != 3:
                raise InputError(file, f"vertex positions of shape {np.asarray(mesh.vertices).shape}, expected (n,3)")
            if len(mesh.vertices) != n:
                raise InputError(file, f"{len(mesh.vertices)} vertices, expected {n} (from {gt_files[0]})")
            if not np.array_equal(np.asarray(mesh.faces), faces):
                raise InputError(file, f"connectivity or vertex order differs from {gt_files[0]}")
            target[k] = mesh.vertices
            if not np.all(np.isfinite(target[k])):
                raise InputError(file, "NaN or infinite vertex positions")
    if poses_file is not None:
        poses = _read_poses(Path(poses_file), len(gt_files))
    else:
        poses = np.arange(len(gt_files), dtype=np.float32)[:, None]
    return save_dataset(out, faces=faces, uv=uv, gt=gt, inferred=inferred, poses=poses,
                        name=name or Path(out).name, rest=gt[0])


def _read_poses(path: Path, k: int) -> np.ndarray:
    if not path.is_file():
        raise InputError(path, "poses file not found")
    if path.suffix == ".npy":
        poses = load_npy(path, mmap=False)
    else:
        try:
            poses = np.loadtxt(path, delimiter="," if path.suffix == ".csv" else None, ndmin=2)
        except (ValueError, OSError, UnicodeDecodeError) as err:
            raise InputError(path, f"cannot read poses ({err})") from None
    if poses.dtype.kind not in "fiu" or poses.ndim == 0:
        raise InputError(path, f"pose vectors must be numbers, got {poses.dtype} of shape {poses.shape}")
    poses = np.asarray(poses, dtype=np.float32).reshape(len(poses), -1)
    if len(poses) != k:
        raise InputError(path, f"{len(poses)} pose rows for {k} meshes")
    if not np.all(np.isfinite(poses)):
        raise InputError(path, "NaN or infinite values")
    return poses
