"""The mvtex-dataset v1 directory (DESIGN §4): load memory-mapped, validate, save, split,
pose selection specs, and import from OBJ/PLY sequences.

    dataset.json   {"format": "mvtex-dataset", "version": 1, "name", "units": "m",
                    "num_poses": K, "num_vertices": n, "pose_dim": P}
                   and "ground_truth": false in an inference set (absent: true)
    mesh.npz       faces int32 (m,3), uv float32 (n,2), optional rest float32 (n,3)
    gt.npy, inferred.npy   float32 (K,n,3); an inference set has no gt.npy
    poses.npy      float32 (K,P)
    split.json     optional {"train": [...], "val": [...], "test": [...]}
    body.npz       optional, with body.npy: faces int32 (mb,3) of the wearer's body (or any
                   opaque thing that is not cloth), counter-clockwise seen from outside
    body.npy       optional, with body.npz: float32 (K,nb,3), row k = the body in pose k
    original_inferred.npy      a corrected set (`mvtex correct`): float32 (K,n,3), the
                               predictor's mesh before the correction (inferred.npy is the
                               corrected one)
    geometry_uncertainty.npy   a corrected set: float32 (K,n), the corrector's predictive
                               standard deviation per vertex, in meters

dataset.json may record the body's size as "body": {"num_vertices": nb, "num_faces": mb};
readers do not require it. A corrected set's dataset.json records the correction under
"correction" (its model, its source dataset and the source's pose of each row).

An *inference set* is a dataset without ground truth: the frames a trained model serves at
run time (the predictor's mesh, the pose, the body). `Dataset.has_gt` says which;
`Dataset.gt` of an inference set raises `NoGroundTruthError`, and `require_gt` is the check
the stages that need gt (slide, eval, bench) make first. `save_dataset(..., gt=None)` writes
one.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from mvtex.data.camera import MAX_COORDINATE_M
from mvtex.util.checks import as_array, as_indices, as_path
from mvtex.util.errors import InputError, NoGroundTruthError, OptionError
from mvtex.util.files import load_npy, load_npz, read_header, read_json, read_row, read_rows
from mvtex.util.fingerprint import fingerprint
from mvtex.util.output import atomic_path, writer

FORMAT = "mvtex-dataset"


VERSION = 1


BODY_FILES = ("body.npz", "body.npy")


GROUND_TRUTH_KEY = "ground_truth"  # dataset.json: false in an inference set; absent means true
ORIGINAL_FILE = "original_inferred.npy"  # a corrected set: the mesh before the correction


UNCERTAINTY_FILE = "geometry_uncertainty.npy"  # a corrected set: the corrector's σ per vertex (m)


@dataclass(frozen=True)
class Body:
    """The wearer's body (or any opaque non-cloth thing), the same under gt and inferred cloth.

    Attributes:
        faces: (mb,3) int32, counter-clockwise seen from outside.
        positions: (K,nb,3) float32, memory-mapped (row k = pose k).
    """

    faces: np.ndarray
    positions: np.ndarray

    def pose(self, k: int) -> np.ndarray:
        """The body's vertices in pose k, (nb,3) float64, read through the file (not the map)."""
        return read_row(self.positions, int(k)).astype(np.float64)

    @property
    def num_vertices(self) -> int:
        return int(self.positions.shape[1])


@dataclass(frozen=True)
class Dataset:
    """A loaded dataset. `gt`, `inferred` are memory-mapped (K,n,3) float32 arrays.

    Attributes:
        path: the dataset directory.
        name: free-form name.
        faces: (m,3) int32. uv: (n,2) float32 (T_G). rest: (n,3) float32 or None.
        inferred: (K,n,3) float32 (memory-mapped). poses: (K,P) float32.
        split: dict with "train", "val", "test" lists of pose indices.
        body: the wearer's body (`Body`), or None when the dataset has no body files.
        ground_truth: (K,n,3) float32 gt positions (memory-mapped), or None in an inference
            set; read it as `gt`, which says what is missing when there is none.
        original_inferred: (K,n,3) float32 (memory-mapped), a corrected set's mesh before
            the correction (`inferred` is the corrected mesh); None for any other dataset.
        geometry_uncertainty: (K,n) float32 (memory-mapped), a corrected set's predictive
            standard deviation of each corrected vertex (m); None for any other dataset.
        correction: dataset.json's "correction" record of a corrected set, else None.
    """

    path: Path
    name: str
    faces: np.ndarray
    uv: np.ndarray
    rest: np.ndarray | None
    inferred: np.ndarray
    poses: np.ndarray
    split: dict[str, list[int]]
    body: Body | None = None
    ground_truth: np.ndarray | None = None

    @property
    def has_gt(self) -> bool:
        """False for an inference set (no gt.npy)."""
        return self.ground_truth is not None

    @property
    def gt(self) -> np.ndarray:
        """(K,n,3) float32 gt positions (memory-mapped).

        Raises:
            NoGroundTruthError: naming the dataset, in an inference set.
        """
        self.require_gt()
        return self.ground_truth

    def require_gt(self, what: str = "this") -> None:
        """Refuse an inference set: `NoGroundTruthError` naming the dataset, what is missing
        and `what` needs it ("slide", "the material error", ...)."""
        if self.ground_truth is None:
            raise NoGroundTruthError(self.path, f"an inference set, no ground truth (gt.npy): {what} needs the "
                                     "ground-truth cloth")
    original_inferred: np.ndarray | None = None
    geometry_uncertainty: np.ndarray | None = None
    correction: dict | None = None

    @property
    def corrected(self) -> bool:
        """True for a corrected set (`mvtex correct`): it keeps the mesh before the
        correction (`original_inferred`) and the corrector's σ (`geometry_uncertainty`)."""
        return self.original_inferred is not None

    @property
    def num_poses(self) -> int:
        return int(self.inferred.shape[0])

    @property
    def num_vertices(self) -> int:
        return int(self.inferred.shape[1])

    def select(self, spec: str | None, default: str = "all") -> list[int]:
        """Pose indices for a SPEC (`all`, `train`, `val`, `test`, `a:b`, `3,5,7`)."""
        return parse_pose_spec(spec or default, self.num_poses, self.split, source=self.path)

    def check_poses(self, poses) -> list[int]:
        """Pose indices as ints; InputError (naming the dataset) when none, one out of range
        or one given twice; OptionError when `poses` is not a list of integers."""

        poses = as_indices(poses, "poses")
        if not poses:
            raise InputError(self.path, "no pose selected")
        _check_range(poses, self.num_poses, self.path)
        if len(set(poses)) != len(poses):
            raise InputError(self.path, f"pose {next(p for p in poses if poses.count(p) > 1)} is selected twice")
        return poses

    def body_arrays(self) -> tuple[np.ndarray, ...]:
        """What the body adds to a content fingerprint: (positions, faces), or () without a body,
        so that a dataset without body files fingerprints as it always did."""
        return () if self.body is None else (self.body.positions, self.body.faces)


def as_dataset(dataset: "Dataset | str | os.PathLike") -> Dataset:
    """A `Dataset` as is, or the dataset directory at a path loaded (`load_dataset`);
    OptionError for anything else."""
    if isinstance(dataset, Dataset):
        return dataset
    if not isinstance(dataset, (str, os.PathLike)):
        raise OptionError("dataset", f"must be a Dataset or a dataset folder path, got {type(dataset).__name__}")
    return load_dataset(dataset)


def reference_shape(dataset: Dataset) -> np.ndarray:
    """The one shape in which pose-independent mesh quantities are measured: seam copies and
    their chart orientation, the fill's Laplacian, edge breaking (`sliding.build_topology`).

    It is the dataset's `rest` shape when it has one, else the gt positions of pose 0
    (`import_sequences` makes the same choice for `rest`), or in an inference set without
    `rest` the inferred positions of pose 0. It never depends on which poses are processed,
    in which order, or by how many workers, so neither do the results.

    Returns:
        (n,3) float64.
    """
    source = reference_shape_source(dataset)
    shape = {"rest": dataset.rest, "gt[0]": dataset.ground_truth, "inferred[0]": dataset.inferred}[source]
    return np.array(shape if source == "rest" else shape[0], dtype=np.float64)


def reference_shape_source(dataset: Dataset) -> str:
    """Which shape `reference_shape` takes: "rest", "gt[0]" or (an inference set without
    rest) "inferred[0]"."""
    if dataset.rest is not None:
        return "rest"
    return "gt[0]" if dataset.has_gt else "inferred[0]"


def content_fingerprint(dataset: Dataset) -> str:
    """The fingerprint (`mvtex.util.fingerprint`) of a dataset's content: gt (where it has
    one), inferred and pose arrays, and the body's when it has one. Texcoord sets and models
    record it, so that they are never used with another dataset's content under the same
    path."""

    # Computed once per loaded dataset: a command that checks a dataset and then uses it
    # reads its arrays once.
    cached = dataset.__dict__.get("_content_fingerprint")
    if cached is None:
        gt = (dataset.ground_truth,) if dataset.has_gt else ()
        cached = fingerprint(*gt, dataset.inferred, dataset.poses, *dataset.body_arrays())
        object.__setattr__(dataset, "_content_fingerprint", cached)
    return cached


def default_split(num_poses: int, seed: int = 0) -> dict[str, list[int]]:
    """A seeded 80/10/10 permutation split of range(num_poses) (the built-in dataset's).

    With 3 or more poses, val and test hold at least one pose each (10 % rounded) and train
    the rest; with fewer, every pose is in train.
    """
    order = np.random.default_rng([seed, 1]).permutation(num_poses)
    n_val = n_test = max(1, round(0.1 * num_poses)) if num_poses >= 3 else 0
    n_train = num_poses - n_val - n_test
    parts = {"train": order[:n_train], "val": order[n_train:n_train + n_val], "test": order[n_train + n_val:]}
    return {name: sorted(int(i) for i in idx) for name, idx in parts.items()}


def _check_range(indices: list[int], num_poses: int, source) -> None:
    bad = [i for i in indices if not 0 <= i < num_poses]
    if bad:
        raise InputError(source, f"pose index {bad[0]} out of range (dataset has {num_poses} poses)")


def parse_pose_spec(spec: str, num_poses: int, split: dict[str, list[int]] | None = None,
                    source: str | os.PathLike | None = None) -> list[int]:
    """Resolve a pose SPEC to sorted-as-given indices; errors raise InputError."""
    spec = str(spec).strip()
    if spec == "all":
        return list(range(num_poses))
    if spec in ("train", "val", "test"):
        split = split if split is not None else default_split(num_poses)
        return list(split[spec])
    try:
        if ":" in spec:
            parts = spec.split(":")
            if len(parts) > 3:
                raise ValueError
            bounds = [int(p) if p.strip() else None for p in parts]
            if bounds[2:] and bounds[2] == 0:
                raise ValueError
            for b in bounds[:2]:
                if b is not None and not -num_poses <= b <= num_poses:
                    raise InputError(source, f"pose spec {spec!r} reaches past the poses of the dataset "
                                     f"(it has {num_poses}: 0..{num_poses - 1})")
            indices = list(range(num_poses))[slice(*bounds)]
        else:
            indices = [int(p) for p in spec.split(",") if p.strip()]
    except InputError:
        raise
    except ValueError:
        raise InputError(source, f"bad pose spec {spec!r} (use all, train, val, test, a:b or 3,5,7)") from None
    _check_range(indices, num_poses, source)
    if len(set(indices)) != len(indices):
        twice = next(i for i in indices if indices.count(i) > 1)
        raise InputError(source, f"pose spec {spec!r} lists pose {twice} twice")
    if not indices:
        raise InputError(source, f"pose spec {spec!r} selects no pose")
    return indices


def validate_mesh(faces: np.ndarray, uv: np.ndarray, source: str | os.PathLike | None) -> None:
    """Faces int (m,3) in range, uv (n,2) finite."""
    faces = np.asarray(faces)
    uv = np.asarray(uv)
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise InputError(source, f"faces must have shape (m,3), got {faces.shape}")
    if not np.issubdtype(faces.dtype, np.integer):
        raise InputError(source, f"faces must be integers, got {faces.dtype}")
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise InputError(source, f"uv must have shape (n,2), got {uv.shape}")
    if uv.dtype.kind != "f":
        raise InputError(source, f"uv must be floating point, got {uv.dtype}")
    if faces.min() < 0 or faces.max() >= len(uv):
        raise InputError(source, f"face index out of range [0, {len(uv)}): min {faces.min()}, max {faces.max()}")
    if not np.all(np.isfinite(uv)):
        raise InputError(source, "uv has NaN or infinite values")


def _check_positions(array: np.ndarray, n: int, source: Path, k: int | None = None) -> None:
    if array.dtype.kind != "f":
        raise InputError(source, f"positions must be float32, got {array.dtype}")
    if array.ndim != 3 or array.shape[2] != 3:
        raise InputError(source, f"expected shape (K,{n},3), got {array.shape}")
    if array.shape[1] != n:
        raise InputError(source, f"vertex count {array.shape[1]} does not match mesh.npz ({n})")
    if k is not None and array.shape[0] != k:
        raise InputError(source, f"pose count {array.shape[0]} does not match ({k})")
    _check_finite(array, source)


def _check_finite(array: np.ndarray, source: Path) -> None:
    """NaN / Inf check of a (K,n,3) array of positions, and their bound (`MAX_COORDINATE_M`),
    naming the first bad pose."""
    # Chunked so a large memory-mapped array is never loaded whole (nor left resident).
    for start in range(0, array.shape[0], 64):
        block = read_rows(array, start, start + 64)
        if not np.all(np.isfinite(block)):
            bad = start + int(np.argmax(~np.isfinite(block).all(axis=(1, 2))))
            raise InputError(source, f"NaN or infinite positions (pose {bad})")
        far = np.abs(block).max(axis=(1, 2), initial=0.0) > MAX_COORDINATE_M
        if far.any():
            bad = int(np.argmax(far))
            raise InputError(source, f"a position of magnitude {np.abs(block[bad]).max():.3g} at pose {start + bad}, "
                             f"more than {MAX_COORDINATE_M:g} m")


def load_dataset(path: str | os.PathLike, validate: bool = True) -> Dataset:
    """Open a dataset directory (arrays memory-mapped); problems raise InputError."""

    path = as_path(path, "path")
    meta = read_header(path, "dataset.json", FORMAT, VERSION, "an mvtex dataset")
    mesh = load_npz(path / "mesh.npz")
    for key in ("faces", "uv"):
        if key not in mesh:
            raise InputError(path / "mesh.npz", f"missing array '{key}'")
    faces, uv = mesh["faces"], mesh["uv"]
    validate_mesh(faces, uv, path / "mesh.npz")
    n = len(uv)
    has_gt = meta.get(GROUND_TRUTH_KEY, True)
    if not isinstance(has_gt, bool):
        raise InputError(path / "dataset.json", f"{GROUND_TRUTH_KEY} must be true or false, got {has_gt!r}")
    if not has_gt and (path / "gt.npy").exists():
        raise InputError(path / "gt.npy", f'is there, but dataset.json says the set has no ground truth '
                         f'("{GROUND_TRUTH_KEY}": false): remove one of them')
    gt = load_npy(path / "gt.npy") if has_gt else None
    inferred = load_npy(path / "inferred.npy")
    poses = load_npy(path / "poses.npy")
    rest = mesh.get("rest")
    if gt is not None and validate:
        _check_positions(gt, n, path / "gt.npy")
    num_poses = gt.shape[0] if gt is not None else (inferred.shape[0] if inferred.ndim else 0)
    if validate:
        _check_positions(inferred, n, path / "inferred.npy", gt.shape[0] if gt is not None else None)
        if not len(inferred):
            raise InputError(path / "inferred.npy", "holds no pose")
        if rest is not None and (rest.shape != (n, 3) or rest.dtype.kind != "f" or not np.all(np.isfinite(rest))):
            raise InputError(path / "mesh.npz", f"rest must be finite with shape ({n},3), got {rest.shape}")
        if poses.dtype.kind != "f":
            raise InputError(path / "poses.npy", f"pose vectors must be float32, got {poses.dtype}")
        if poses.ndim != 2 or poses.shape[0] != num_poses:
            raise InputError(path / "poses.npy", f"expected shape ({num_poses},P), got {poses.shape}")
        if not np.all(np.isfinite(poses)):
            raise InputError(path / "poses.npy", "NaN or infinite values")
        for key, expected in (("num_poses", num_poses), ("num_vertices", n), ("pose_dim", poses.shape[1])):
            if key in meta and (type(meta[key]) is not int or meta[key] != expected):
                raise InputError(path / "dataset.json", f"{key} is {meta[key]} but the arrays say {expected}")
    body = _load_body(path, num_poses, meta, validate)
    split = _load_split(path, num_poses)
    original, sigma, correction = _load_correction(path, inferred.shape, meta, validate)
    return Dataset(path=path, name=str(meta.get("name", path.name)), faces=faces.astype(np.int32),
                   uv=uv.astype(np.float32), rest=None if rest is None else rest.astype(np.float32),
                   ground_truth=gt, inferred=inferred, poses=poses, split=split, body=body, original_inferred=original,
                   geometry_uncertainty=sigma, correction=correction)


def _load_correction(path: Path, shape: tuple[int, ...], meta: dict, validate: bool
                     ) -> tuple[np.ndarray | None, np.ndarray | None, dict | None]:
    """A corrected set's original_inferred.npy and geometry_uncertainty.npy (both or
    neither) and its "correction" record; checked like gt (never loaded whole)."""
    present = [(path / name).is_file() for name in (ORIGINAL_FILE, UNCERTAINTY_FILE)]
    if not any(present):
        return None, None, None
    if not all(present):
        have, missing = (ORIGINAL_FILE, UNCERTAINTY_FILE) if present[0] else (UNCERTAINTY_FILE, ORIGINAL_FILE)
        raise InputError(path / missing, f"file not found ({have} is there: a corrected set needs both files)")
    original = load_npy(path / ORIGINAL_FILE)
    sigma = load_npy(path / UNCERTAINTY_FILE)
    if original.dtype != np.float32 or original.shape != tuple(shape):
        raise InputError(path / ORIGINAL_FILE, f"expected float32 of shape {tuple(shape)} (as inferred.npy), "
                         f"got {original.dtype} {original.shape}")
    if sigma.dtype != np.float32 or sigma.shape != tuple(shape[:2]):
        raise InputError(path / UNCERTAINTY_FILE, f"expected float32 of shape {tuple(shape[:2])}, "
                         f"got {sigma.dtype} {sigma.shape}")
    correction = meta.get("correction")
    if correction is not None and not isinstance(correction, dict):
        raise InputError(path / "dataset.json", f"correction must be an object, got {correction!r:.60}")
    if validate:
        _check_finite(original, path / ORIGINAL_FILE)
        for start in range(0, sigma.shape[0], 256):
            block = read_rows(sigma, start, start + 256)
            if not np.all(np.isfinite(block) & (block >= 0)):
                raise InputError(path / UNCERTAINTY_FILE, "negative, NaN or infinite standard deviations "
                                 f"(pose {start + int(np.argmax(~(np.isfinite(block) & (block >= 0)).all(1)))})")
    return original, sigma, correction


def validate_body_faces(faces: np.ndarray, num_vertices: int, source: str | os.PathLike | None) -> None:
    """Body faces: integers of shape (mb,3), mb >= 1, indices in [0, num_vertices)."""
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise InputError(source, f"body faces must have shape (mb,3), got {faces.shape}")
    if not np.issubdtype(faces.dtype, np.integer):
        raise InputError(source, f"body faces must be integers, got {faces.dtype}")
    if faces.min() < 0 or faces.max() >= num_vertices:
        raise InputError(source, f"body face index out of range [0, {num_vertices}): min {faces.min()}, "
                         f"max {faces.max()}")


def _load_body(path: Path, num_poses: int, meta: dict, validate: bool) -> Body | None:
    """body.npz + body.npy, both or neither; checked like gt (never loaded whole)."""
    present = [(path / name).is_file() for name in BODY_FILES]
    if not any(present):
        return None
    if not all(present):
        have, missing = (BODY_FILES[0], BODY_FILES[1]) if present[0] else (BODY_FILES[1], BODY_FILES[0])
        raise InputError(path / missing, f"file not found ({have} is there: the body needs both files)")
    archive = load_npz(path / "body.npz")
    if "faces" not in archive:
        raise InputError(path / "body.npz", "missing array 'faces'")
    faces = archive["faces"]
    positions = load_npy(path / "body.npy")
    file = path / "body.npy"
    if positions.dtype != np.float32:
        raise InputError(file, f"body positions must be float32, got {positions.dtype}")
    if positions.ndim != 3 or positions.shape[2] != 3 or positions.shape[1] == 0:
        raise InputError(file, f"expected shape (K,nb,3), got {positions.shape}")
    if positions.shape[0] != num_poses:
        raise InputError(file, f"pose count {positions.shape[0]} does not match inferred.npy ({num_poses})")
    validate_body_faces(faces, positions.shape[1], path / "body.npz")
    if validate:
        _check_finite(positions, file)
        record = meta.get("body")
        if record is not None:
            expected = {"num_vertices": positions.shape[1], "num_faces": len(faces)}
            if not isinstance(record, dict):
                raise InputError(path / "dataset.json", f"body must be an object, got {record!r}")
            for key, value in expected.items():
                if key in record and (type(record[key]) is not int or record[key] != value):
                    raise InputError(path / "dataset.json",
                                     f"body {key} is {record[key]} but the body files say {value}")
    return Body(faces=faces.astype(np.int32), positions=positions)


def _load_split(path: Path, num_poses: int) -> dict[str, list[int]]:
    file = path / "split.json"
    if not file.exists():
        return default_split(num_poses)
    split = read_json(file)
    if not isinstance(split, dict) or not all(k in split for k in ("train", "val", "test")):
        raise InputError(file, "needs lists 'train', 'val' and 'test'")
    out = {}
    for key in ("train", "val", "test"):
        values = split[key]
        if not isinstance(values, list) or not all(type(i) is int for i in values):
            raise InputError(file, f"'{key}' must be a list of integer pose indices")
        if any(not 0 <= i < num_poses for i in values):
            raise InputError(file, f"'{key}' has a pose index outside [0, {num_poses})")
        out[key] = values
    return out


def check_body_arrays(body_faces, body, num_poses: int, source: str | os.PathLike | None) -> None:
    """What `save_dataset` accepts as a body: both or neither; (mb,3) faces in range and
    (K,nb,3) finite positions with K = num_poses."""
    if (body_faces is None) != (body is None):
        raise InputError(source, "a body needs both body_faces and body positions (or neither)")
    if body is None:
        return
    shape = np.shape(body)
    if len(shape) != 3 or shape[2] != 3 or shape[1] == 0 or shape[0] != num_poses:
        raise InputError(source, f"body positions must be ({num_poses},nb,3), got {shape}")
    validate_body_faces(body_faces, shape[1], source)


def metadata(name: str, num_poses: int, num_vertices: int, pose_dim: int, body_faces=None, body=None,
             ground_truth: bool = True, **extra_meta) -> dict:
    """dataset.json's content, in the order `save_dataset` writes it ("ground_truth": false
    only in an inference set)."""
    meta = {"format": FORMAT, "version": VERSION, "name": name, "units": "m", "num_poses": int(num_poses),
            "num_vertices": int(num_vertices), "pose_dim": int(pose_dim)}
    if not ground_truth:
        meta[GROUND_TRUTH_KEY] = False
    if body is not None:
        meta["body"] = {"num_vertices": int(np.shape(body)[1]), "num_faces": int(len(body_faces))}
    return {**meta, **extra_meta}


@writer("save_dataset", out="path", inputs=lambda a: (a["gt"], a["inferred"], a["poses"], a["body"]))
def save_dataset(path: str | os.PathLike, *, faces: np.ndarray, uv: np.ndarray, gt: np.ndarray | None,
                 inferred: np.ndarray, poses: np.ndarray, name: str = "dataset",
                 rest: np.ndarray | None = None, split: dict[str, Sequence[int]] | None = None,
                 body_faces: np.ndarray | None = None, body: np.ndarray | None = None, overwrite: bool = False,
                 **extra_meta) -> Path:
    """Write a dataset directory atomically (the whole directory appears at once), under
    the writer policy (`mvtex.util.output`): an existing folder is replaced only when mvtex
    wrote all it holds (another command's output only with `overwrite`), never an input.

    Everything `load_dataset` checks is checked first (shapes, finite values, the split's
    pose indices, the body), so that a dataset written is a dataset that loads.

    Args:
        faces: (m,3) int. uv: (n,2). gt, inferred: (K,n,3). poses: (K,P).
        gt: None writes an inference set (no gt.npy, "ground_truth": false in
            dataset.json): the run-time frames of a trained model.
        rest: optional (n,3); an inference set's measures against the rest shape (strain,
            the triangulation's fill) take the first inferred frame without it.
        split: optional train/val/test lists (default 80/10/10).
        body_faces: optional (mb,3) int, and body: optional (K,nb,3): the wearer's body
            (both or neither), written as body.npz and body.npy.
        extra_meta: extra JSON-serialisable keys for dataset.json (e.g. "stats").

    Raises:
        OptionError: naming the argument of a wrong type, shape or value.
    """

    path = as_path(path, "path")
    if not isinstance(name, str):
        raise OptionError("name", f"must be a string, got {type(name).__name__}")
    faces, uv = as_array(faces, "faces", None), as_array(uv, "uv", None)
    gt = None if gt is None else as_array(gt, "gt", np.float32)
    inferred = as_array(inferred, "inferred", np.float32)
    poses = as_array(poses, "poses", np.float32)
    try:
        validate_mesh(faces, uv, None)
    except InputError as err:
        raise OptionError(None, f"faces/uv: {err.problem}") from None
    if inferred.ndim != 3 or inferred.shape[1:] != (len(uv), 3) or not len(inferred):
        raise OptionError("inferred", f"must have shape (K,{len(uv)},3) with K ≥ 1, got {inferred.shape}")
    if gt is not None and gt.shape != inferred.shape:
        raise OptionError("gt", f"and inferred must both have shape (K,{len(uv)},3) with K ≥ 1, got {gt.shape} and "
                          f"{inferred.shape}")
    num_poses = len(inferred)
    if body is not None:
        body = as_array(body, "body", np.float32)
    if poses.ndim == 1 and len(poses) == num_poses:
        poses = poses[:, None]
    if poses.ndim != 2 or len(poses) != num_poses or poses.shape[1] == 0:
        raise OptionError("poses", f"must have shape ({num_poses},P), got {poses.shape}")
    for key, array in (("gt", gt), ("inferred", inferred), ("poses", poses), ("body", body)):
        if array is None:
            continue
        if not np.all(np.isfinite(array)):
            raise OptionError(key, "has NaN or infinite values (float32)")
        if key != "poses" and array.size and np.abs(array).max() > MAX_COORDINATE_M:
            raise OptionError(key, f"has a position of magnitude {np.abs(array).max():.3g}, more than "
                              f"{MAX_COORDINATE_M:g} m")
    if rest is not None:
        rest = as_array(rest, "rest", np.float32)
        if rest.shape != (len(uv), 3) or not np.all(np.isfinite(rest)):
            raise OptionError("rest", f"must be finite with shape ({len(uv)},3), got {rest.shape}")
    if split is not None:
        if not isinstance(split, dict) or not all(k in split for k in ("train", "val", "test")):
            raise OptionError("split", "must be a dict with lists 'train', 'val' and 'test'")

        split = {k: as_indices(split[k], f"split[{k!r}]") for k in ("train", "val", "test")}
        if any(not 0 <= i < num_poses for k in split for i in split[k]):
            raise OptionError("split", f"has a pose index outside [0, {num_poses})")
    if body_faces is not None:
        body_faces = as_array(body_faces, "body_faces", None)
    try:
        check_body_arrays(body_faces, body, num_poses, None)
    except InputError as err:
        raise OptionError(None, f"body: {err.problem}") from None
    check_body_arrays(body_faces, body, num_poses, path)
    if body is not None and not np.all(np.isfinite(body)):
        raise OptionError("body", "positions have NaN or infinite values")
    if GROUND_TRUTH_KEY in extra_meta:
        raise OptionError("extra_meta", f"sets {GROUND_TRUTH_KEY}, which gt sets (None: an inference set)")
    split = split or default_split(num_poses)
    meta = metadata(name, num_poses, len(uv), poses.shape[1], body_faces, body, ground_truth=gt is not None,
                    **extra_meta)
    with atomic_path(path) as tmp:
        tmp.mkdir()
        mesh = {"faces": np.asarray(faces, dtype=np.int32), "uv": np.asarray(uv, dtype=np.float32)}
        if rest is not None:
            mesh["rest"] = np.asarray(rest, dtype=np.float32)
        np.savez_compressed(tmp / "mesh.npz", **mesh)
        if gt is not None:
            np.save(tmp / "gt.npy", gt, allow_pickle=False)
        np.save(tmp / "inferred.npy", inferred, allow_pickle=False)
        np.save(tmp / "poses.npy", poses, allow_pickle=False)
        if body is not None:
            np.savez_compressed(tmp / "body.npz", faces=np.asarray(body_faces, dtype=np.int32))
            np.save(tmp / "body.npy", body, allow_pickle=False)
        (tmp / "split.json").write_text(json.dumps({k: [int(i) for i in split[k]] for k in ("train", "val", "test")}) + "\n")
        (tmp / "dataset.json").write_text(json.dumps(meta, indent=2) + "\n")
    return path
