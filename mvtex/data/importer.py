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


def _check_same_mesh(mesh, file: str, n: int, faces: np.ndarray, first: str) -> np.ndarray:
    """The vertices (n,3) float32 of a mesh of a sequence whose first mesh (`first`) has n vertices
    and these faces; InputError naming `file` otherwise."""
    vertices = np.asarray(mesh.vertices)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise InputError(file, f"vertex positions of shape {vertices.shape}, expected (n,3)")
    if len(vertices) != n:
        raise InputError(file, f"{len(vertices)} vertices, expected {n} (from {first})")
    if not np.array_equal(np.asarray(mesh.faces), faces):
        raise InputError(file, f"connectivity or vertex order differs from {first}")
    vertices = vertices.astype(np.float32)
    if not np.all(np.isfinite(vertices)):  # after the cast: float32 overflows count too
        raise InputError(file, "NaN or infinite vertex positions")
    return vertices


def _read_body(files: list[str], progress: bool) -> tuple[np.ndarray, np.ndarray]:
    """A body sequence: (faces (mb,3) int32, positions (K,nb,3) float32); no uv needed."""
    count = len(files)
    first = _read_mesh(files[0])
    faces = np.asarray(first.faces, dtype=np.int32)
    nb = len(first.vertices)
    positions = np.empty((count, nb, 3), dtype=np.float32)
    from tqdm import tqdm

    for k, file in enumerate(tqdm(files, desc="import body", unit="pose", disable=not progress)):
        mesh = first if k == 0 else _read_mesh(file)
        positions[k] = _check_same_mesh(mesh, file, nb, faces, files[0])
    return faces, positions


def import_sequences(out: str | os.PathLike, gt_glob: str, inferred_glob: str,
                     poses_file: str | os.PathLike | None = None, name: str | None = None,
                     progress: bool = True, body_glob: str | None = None) -> Path:
    """Turn two OBJ/PLY sequences with identical connectivity into a dataset.

    Files are paired in sorted order. The first gt mesh defines faces and uv (and `rest`);
    every other mesh must have the same vertex count and the same faces, or InputError.
    Without `poses_file` (.npy (K,P) or .txt/.csv rows), the pose vector is the frame index.
    With `body_glob`, a third sequence (one connectivity, no uv needed, as many meshes as
    gt, paired in sorted order) becomes the dataset's body (body.npz + body.npy).
    """
    gt_files = _sorted_glob(gt_glob, "gt")
    inf_files = _sorted_glob(inferred_glob, "inferred")
    if len(gt_files) != len(inf_files):
        raise InputError(inferred_glob, f"{len(inf_files)} inferred meshes for {len(gt_files)} gt meshes")
    body_files = _sorted_glob(body_glob, "body") if body_glob is not None else None
    if body_files is not None and len(body_files) != len(gt_files):
        raise InputError(body_glob, f"{len(body_files)} body meshes for {len(gt_files)} gt meshes")
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
            target[k] = _check_same_mesh(mesh, file, n, faces, gt_files[0])
    if poses_file is not None:
        poses = _read_poses(Path(poses_file), len(gt_files))
    else:
        poses = np.arange(len(gt_files), dtype=np.float32)[:, None]
    body_faces, body = _read_body(body_files, progress) if body_files is not None else (None, None)
    return save_dataset(out, faces=faces, uv=uv, gt=gt, inferred=inferred, poses=poses,
                        name=name or Path(out).name, rest=gt[0], body_faces=body_faces, body=body)


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
