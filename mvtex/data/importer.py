"""`mvtex import`: OBJ/PLY sequences with one connectivity -> an mvtex dataset, or without
ground-truth meshes an inference set (DESIGN §4): the frames a trained model serves.
"""

from __future__ import annotations

import glob
import glob as globlib
import logging
import os
import warnings
from pathlib import Path

import numpy as np
from tqdm import tqdm

from mvtex.data.camera import MAX_COORDINATE_M
from mvtex.data.dataset import save_dataset, validate_body_faces
from mvtex.util.checks import as_path
from mvtex.util.errors import InputError, OptionError
from mvtex.util.files import load_npy
from mvtex.util.output import writer

MESH_SUFFIXES = (".obj", ".ply")


def _sorted_glob(pattern: str, what: str) -> list[str]:
    files = sorted(f for f in globlib.glob(pattern) if not os.path.isdir(f))
    if not files:
        raise InputError(pattern, f"no {what} files match")
    stray = [f for f in files if Path(f).suffix.lower() not in MESH_SUFFIXES]
    if stray:
        raise InputError(stray[0], f"matches the {what} glob {pattern!r} but is not an OBJ or PLY file; "
                         "narrow the glob")
    return files


def _check_obj_text(file: str) -> None:
    """What trimesh would read silently differently, in one line: bytes that are not text,
    faces that are not triangles, face indices out of range."""
    try:
        text = Path(file).read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        raise InputError(file, "is not a text OBJ file (it does not decode as UTF-8)") from None
    lines = text.splitlines()
    total = sum(1 for line in lines if line.startswith("v "))
    vertices = 0  # defined so far: negative indices count back from here
    for number, line in enumerate(lines, start=1):
        fields = line.split()
        if not fields:
            continue
        if fields[0] == "v":
            vertices += 1
        elif fields[0] == "f":
            if len(fields) != 4:
                raise InputError(file, f"line {number}: a face of {len(fields) - 1} vertices; mvtex reads "
                                 "triangle meshes (triangulate it first)")
            for ref in fields[1:]:
                try:
                    index = int(ref.split("/")[0])
                except ValueError:
                    raise InputError(file, f"line {number}: bad face vertex {ref!r}") from None
                if not (1 <= index <= total or -vertices <= index <= -1):
                    raise InputError(file, f"line {number}: face vertex {index} out of range (the file has "
                                     f"{total} vertices)")


def _ply_face_count(file: str) -> int | None:
    """The face count a PLY header declares (None when not readable as a PLY header)."""
    with open(file, "rb") as f:
        head = f.read(4096)
    if not head.startswith(b"ply"):
        return None
    for line in head.split(b"end_header")[0].splitlines():
        fields = line.split()
        if fields[:2] == [b"element", b"face"] and len(fields) == 3 and fields[2].isdigit():
            return int(fields[2])
    return None


def _read_mesh(file: str):

    import trimesh  # noqa: PLC0415 (loaded on use)

    if Path(file).suffix.lower() == ".obj":
        _check_obj_text(file)
    log = logging.getLogger("trimesh")
    level = log.level
    log.setLevel(logging.CRITICAL)  # its warnings would be lines besides mvtex's one-line error
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mesh = trimesh.load(file, process=False, maintain_order=True, force="mesh")
    except Exception as err:  # trimesh raises many kinds for unreadable files
        raise InputError(file, f"cannot read mesh ({type(err).__name__}: {err})") from None
    finally:
        log.setLevel(level)
    if not hasattr(mesh, "faces") or len(mesh.faces) == 0:
        raise InputError(file, "no triangle faces")
    declared = _ply_face_count(file) if Path(file).suffix.lower() == ".ply" else None
    if declared is not None and declared != len(mesh.faces):
        raise InputError(file, f"declares {declared} faces that make {len(mesh.faces)} triangles: mvtex reads "
                         "triangle meshes (triangulate it first)")
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
    with np.errstate(over="ignore", invalid="ignore"):
        vertices = vertices.astype(np.float32)
    if not np.all(np.isfinite(vertices)):  # after the cast: float32 overflows count too
        raise InputError(file, "NaN or infinite vertex positions")
    if vertices.size and np.abs(vertices).max() > MAX_COORDINATE_M:
        raise InputError(file, f"a vertex position of magnitude {np.abs(vertices).max():.3g}, more than "
                         f"{MAX_COORDINATE_M:g} m")
    return vertices


def _read_body(files: list[str], progress: bool) -> tuple[np.ndarray, np.ndarray]:
    """A body sequence: (faces (mb,3) int32, positions (K,nb,3) float32); no uv needed."""
    count = len(files)
    first = _read_mesh(files[0])
    faces = np.asarray(first.faces, dtype=np.int32)
    nb = len(first.vertices)
    validate_body_faces(faces, nb, files[0])  # the body's own file named, not the dataset being made
    positions = np.empty((count, nb, 3), dtype=np.float32)

    for k, file in enumerate(tqdm(files, desc="import body", unit="pose", disable=not progress)):
        mesh = first if k == 0 else _read_mesh(file)
        positions[k] = _check_same_mesh(mesh, file, nb, faces, files[0])
    return faces, positions


def _inputs(a: dict) -> list:

    # Only what names files: an argument of another type is refused by the function itself.
    named = [a[k] for k in ("gt_glob", "inferred_glob", "body_glob") if isinstance(a[k], (str, os.PathLike))]
    files = [a[k] if isinstance(a[k], (str, os.PathLike)) else None for k in ("poses_file", "rest_mesh")]
    return [glob.glob(os.fspath(g)) for g in named] + files


@writer("import", inputs=_inputs)
def import_sequences(out: str | os.PathLike, gt_glob: str | None = None, inferred_glob: str | None = None,
                     poses_file: str | os.PathLike | None = None, name: str | None = None,
                     progress: bool = True, body_glob: str | None = None, overwrite: bool = False,
                     rest_mesh: str | os.PathLike | None = None) -> Path:
    """Turn OBJ/PLY sequences with identical connectivity into a dataset, or without
    `gt_glob` into an inference set (no gt.npy; DESIGN §4).

    Files are paired in sorted order. The first mesh of the first sequence (gt, or inferred
    without gt) defines faces and uv; every other mesh must have the same vertex count and
    the same faces, or InputError. The rest shape is `rest_mesh` (an OBJ/PLY of the same
    connectivity) when given, else the first gt mesh, or without gt the first inferred mesh:
    the material error needs a true rest shape (and gt); with the first inferred frame as
    rest, strain and the triangulation's fill are measured on that frame.
    Without `poses_file` (.npy (K,P) or .txt/.csv rows), the pose vector is the frame index.
    With `body_glob`, another sequence (one connectivity, no uv needed, one mesh per frame,
    paired in sorted order) becomes the dataset's body (body.npz + body.npy).

    Raises:
        InputError: naming the file: no match, a mesh of another vertex count or
            connectivity, NaN, pose rows or body meshes of another frame count.
    """

    out = as_path(out, "out")
    poses_file = as_path(poses_file, "poses_file", optional=True)
    rest_mesh = as_path(rest_mesh, "rest_mesh", optional=True)
    for key, value in (("gt_glob", gt_glob), ("inferred_glob", inferred_glob), ("body_glob", body_glob),
                       ("name", name)):
        if value is not None and not isinstance(value, str) or value is None and key == "inferred_glob":
            raise OptionError(key, f"must be a string, got {type(value).__name__}")
    gt_files = _sorted_glob(gt_glob, "gt") if gt_glob is not None else None
    inf_files = _sorted_glob(inferred_glob, "inferred")
    if gt_files is not None and len(gt_files) != len(inf_files):
        raise InputError(inferred_glob, f"{len(inf_files)} inferred meshes for {len(gt_files)} gt meshes")
    frames = "gt" if gt_files is not None else "inferred"
    body_files = _sorted_glob(body_glob, "body") if body_glob is not None else None
    if body_files is not None and len(body_files) != len(inf_files):
        raise InputError(body_glob, f"{len(body_files)} body meshes for {len(inf_files)} {frames} meshes")
    poses = _read_poses(Path(poses_file), len(inf_files)) if poses_file is not None else \
        np.arange(len(inf_files), dtype=np.float32)[:, None]
    source = (gt_files or inf_files)[0]
    first = _read_mesh(source)
    faces = np.asarray(first.faces, dtype=np.int32)
    n = len(first.vertices)
    uv = getattr(getattr(first, "visual", None), "uv", None)
    if uv is None or len(uv) != n:
        raise InputError(source, "no per-vertex texture coordinates (need OBJ 'vt' or PLY texcoords)")
    uv = np.asarray(uv, dtype=np.float32)
    if not np.all(np.isfinite(uv)):
        raise InputError(source, "NaN or infinite texture coordinates")
    rest = None
    if rest_mesh is not None:
        if not Path(rest_mesh).is_file():
            raise InputError(rest_mesh, "rest mesh not found")
        rest = _check_same_mesh(_read_mesh(os.fspath(rest_mesh)), os.fspath(rest_mesh), n, faces, source)
    gt = np.empty((len(inf_files), n, 3), dtype=np.float32) if gt_files is not None else None
    inferred = np.empty((len(inf_files), n, 3), dtype=np.float32)

    pairs = list(zip(gt_files or [None] * len(inf_files), inf_files))
    for k, (g, i) in enumerate(tqdm(pairs, desc="import", unit="pose", disable=not progress)):
        for file, target in ((g, gt), (i, inferred)):
            if file is not None:
                mesh = first if file == source else _read_mesh(file)
                target[k] = _check_same_mesh(mesh, file, n, faces, source)
    body_faces, body = _read_body(body_files, progress) if body_files is not None else (None, None)
    if rest is None:
        rest = gt[0] if gt is not None else inferred[0]
    return save_dataset(out, faces=faces, uv=uv, gt=gt, inferred=inferred, poses=poses,
                        name=name or Path(out).name, rest=rest, body_faces=body_faces, body=body)


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
