"""The texcoord set (DESIGN §4): the hub format that slide, predict and views write and
eval, triangulate, render, views and preview read.

    texcoords.json   {"format": "mvtex-texcoords", "version": 1, "source": "ts"|"tsnn"|...,
                      "subdiv": s, "poses": [...], "cameras": [...], ...}
    mesh.npz         faces int32 (m',3), uv float32 (n',2) (T_G on the subdivided mesh),
                     parent int32 (n',2)
    <camera>/displacement.npy  float32 (len(poses), n', 2): d = T_N - T_G
    <camera>/assigned.npy      bool (len(poses), n')
    <camera>/uncertainty.npy   optional float32 (len(poses), n'): the predictive standard
                               deviation of d per vertex (uv units), written by models that
                               report one; checked (`check_uncertainty`) wherever the
                               camera is read, used where it is wanted

texcoords.json is `mvtex.data.texcoord_header.TexcoordHeader`; the resumable writer of
`slide` and `views` is `mvtex.data.partial_set.PartialSet`.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from mvtex.data.camera import check_camera_name
from mvtex.data.dataset import content_fingerprint, validate_mesh
from mvtex.data.mesh import apply_extension, extension_matrix
from mvtex.data.texcoord_header import FORMAT, MAX_SUBDIV, VERSION, TexcoordHeader
from mvtex.util.checks import as_index, as_path
from mvtex.util.errors import InputError, OptionError
from mvtex.util.files import load_npy, load_npz, read_row, read_rows
from mvtex.util.fingerprint import fingerprint
from mvtex.util.output import atomic_path, writer

__all__ = ["FORMAT", "LAYOUT", "MAX_DISPLACEMENT", "MAX_SUBDIV", "RIG_FILE", "UNCERTAINTY_DTYPE", "VERSION",
           "TexcoordSet", "as_texcoords", "check_texcoord_arrays", "check_uncertainty", "dataset_record",
           "open_texcoords", "recorded_rig", "rig_record", "save_texcoords", "write_header"]

LAYOUT = ["texcoords.json", "mesh.npz", "rig.yaml"]
"""The files of a set beside its camera folders."""

MAX_DISPLACEMENT = 1.0
"""Largest |d| accepted in a set (uv units: the whole atlas is 1 wide); larger is corrupt."""

UNCERTAINTY_DTYPE = np.dtype("<f4")
"""What `<camera>/uncertainty.npy` holds: float32, little-endian."""


@dataclass(frozen=True)
class TexcoordSet:
    """An opened texcoord set; per-camera arrays are memory-mapped on first access.

    Attributes:
        path: the directory. header: its texcoords.json (`TexcoordHeader`).
        faces: (m',3) int32. uv: (n',2) float32 T_G on the (subdivided) mesh. parent: (n',2) int32.
    """

    path: Path
    header: TexcoordHeader
    faces: np.ndarray
    uv: np.ndarray
    parent: np.ndarray
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def meta(self) -> dict[str, Any]:
        """texcoords.json as a dict."""
        return self.header.to_json()

    @property
    def poses(self) -> list[int]:
        return list(self.header.poses)

    @property
    def cameras(self) -> list[str]:
        return list(self.header.cameras)

    @property
    def subdiv(self) -> int:
        return self.header.subdiv

    @property
    def source(self) -> str:
        return self.header.source

    @property
    def num_base_vertices(self) -> int:
        return int(np.sum(self.parent[:, 0] == self.parent[:, 1]))

    def row(self, pose: int) -> int:
        """Row of a dataset pose index in the per-camera arrays."""
        try:
            return self.poses.index(int(pose))
        except ValueError:
            raise InputError(self.path / "texcoords.json", f"pose {pose} is not in this texcoord set "
                             f"(it has {len(self.poses)} poses)") from None

    def _arrays(self, camera: str) -> tuple[np.ndarray, np.ndarray]:
        if camera not in self._cache:
            if camera not in self.cameras:
                raise InputError(self.path, f"no camera {camera!r} in this texcoord set (it has {', '.join(self.cameras)})")
            d = load_npy(self.path / camera / "displacement.npy")
            a = load_npy(self.path / camera / "assigned.npy")
            shape = (len(self.poses), len(self.uv))
            if d.shape != shape + (2,):
                raise InputError(self.path / camera / "displacement.npy", f"shape {d.shape}, expected {shape + (2,)}")
            if a.shape != shape or a.dtype != np.bool_:
                raise InputError(self.path / camera / "assigned.npy", f"shape {a.shape} {a.dtype}, expected {shape} bool")
            if d.dtype.kind != "f":
                raise InputError(self.path / camera / "displacement.npy", f"dtype {d.dtype}, expected float32")
            _check_displacements(d, self.path / camera / "displacement.npy")
            self._cache[("uncertainty", camera)] = self._read_uncertainty(camera)
            self._cache[camera] = (d, a)
        return self._cache[camera]

    def _read_uncertainty(self, camera: str) -> np.ndarray | None:
        """The camera's uncertainty.npy, checked (`check_uncertainty`), or None without one.
        Every command that reads a camera checks it, whether it uses it or not."""
        file = self.path / camera / "uncertainty.npy"
        if not os.path.lexists(file):
            return None
        if not file.is_file():
            raise InputError(file, "is not a file (a folder, a device or a broken link?): the uncertainty of a "
                             "texcoord set is a .npy file")
        u = load_npy(file)
        check_uncertainty(u, (len(self.poses), len(self.uv)), lambda problem, row: InputError(
            file, problem if row is None else f"{problem} at row {row} (pose {self.poses[row]})"))
        return u

    # Rows are read through the files (`read_rows`), not the maps: pages read through a map
    # stay resident while it lives, so a pass over a 10,000-pose set would hold all of it.
    def displacement(self, camera: str, pose: int) -> np.ndarray:
        """d = T_N - T_G, (n',2) float32, for a dataset pose index (a copy)."""
        return read_row(self._arrays(camera)[0], self.row(pose))

    def assigned(self, camera: str, pose: int) -> np.ndarray:
        """(n',) bool: True where d came from the ray (a copy)."""
        return read_row(self._arrays(camera)[1], self.row(pose))

    def _uncertainty(self, camera: str) -> np.ndarray | None:
        self._arrays(camera)  # the camera exists and its arrays are sound
        return self._cache[("uncertainty", camera)]

    def has_uncertainty(self, camera: str) -> bool:
        """True when the set holds the camera's predictive uncertainty (`uncertainty`)."""
        return self._uncertainty(camera) is not None

    def uncertainty(self, camera: str, pose: int) -> np.ndarray | None:
        """The predictive standard deviation of d per vertex, (n',) float32 in uv units (the
        root of the expected squared length of d's error), or None when the set has none for
        this camera (slid sets, models that report none)."""
        u = self._uncertainty(camera)
        return None if u is None else read_row(u, self.row(pose))

    def fingerprint(self, camera: str) -> str:
        """Content hash of one camera's displacement and assigned arrays (`io.fingerprint`,
        read in blocks through the files)."""

        return fingerprint(*self._arrays(camera))

    def texcoords(self, camera: str, pose: int) -> np.ndarray:
        """T_N = T_G + d, (n',2) float32."""
        return self.uv + self.displacement(camera, pose)

    def check_dataset(self, dataset) -> None:
        """Refuse (InputError) a dataset other than the one this set was made from: its mesh
        (vertex count, and the fingerprint of faces and uv where recorded) and its content
        (`mvtex.data.dataset.content_fingerprint`, where recorded)."""

        header = self.path / "texcoords.json"
        if self.num_base_vertices != dataset.num_vertices:
            raise InputError(self.path / "mesh.npz", f"made for a mesh of {self.num_base_vertices} vertices, the dataset "
                             f"{dataset.path} has {dataset.num_vertices}")
        recorded = self.meta.get("dataset")
        if not isinstance(recorded, dict):
            return
        if "mesh" in recorded and recorded["mesh"] not in (fingerprint(dataset.faces, dataset.uv),
                                                           _mesh_fingerprint_0_1(dataset.faces, dataset.uv)):
            raise InputError(header, f"was made for another mesh than that of {dataset.path} (faces or uv differ)")
        if "content" in recorded and recorded["content"] != content_fingerprint(dataset):
            raise InputError(header, f"was made from another dataset than {dataset.path} (its gt, inferred or pose "
                             "arrays differ): make the set again from this dataset")

    def check_rig(self, rig, cameras: Sequence[str] | None = None) -> None:
        """Refuse (InputError) a rig that lacks the set's cameras (or `cameras` of them), or
        whose cameras of those names differ from the ones the set was made with (where it
        records them: size, K, R, t to 1e-6)."""
        names = list(self.cameras if cameras is None else cameras)
        where = f" {rig.source}" if rig.source else ""
        missing = [c for c in names if c not in rig.names]
        if missing:
            raise InputError(self.path, f"cameras {', '.join(missing)} of this texcoord set are not in the rig{where} "
                             f"(it has {', '.join(rig.names)}): a texcoord set of another rig?")
        recorded = self.meta.get("rig")
        if not isinstance(recorded, dict):
            return
        for name in names:
            rec = recorded.get(name)
            if not isinstance(rec, dict):
                continue
            cam = rig[name]
            try:
                same = (int(rec["width"]) == cam.width and int(rec["height"]) == cam.height
                        and np.allclose(rec["K"], cam.K, atol=1e-6) and np.allclose(rec["R"], cam.R, atol=1e-6)
                        and np.allclose(rec["t"], cam.t, atol=1e-6))
            except (KeyError, TypeError, ValueError):
                same = False
            if not same:
                raise InputError(self.path / "texcoords.json", f"camera {name!r} of this set was made with other "
                                 f"parameters than the rig's{where} camera of that name")

    def positions(self, positions: np.ndarray) -> np.ndarray:
        """Extend base-mesh positions (n,3) (or (K,n,3)) to this set's subdivided mesh."""
        if ("extension",) not in self._cache:  # camera names are strings: no clash
            self._cache[("extension",)] = extension_matrix(self.parent)
        return apply_extension(self._cache[("extension",)], positions)


def _mesh_fingerprint_0_1(faces: np.ndarray, uv: np.ndarray) -> str:
    """The "mesh" fingerprint texcoord sets of mvtex 0.1 recorded (SHA-1 of shapes, dtypes and
    bytes), so that `check_dataset` reads them."""

    h = hashlib.sha1()
    for a in (np.ascontiguousarray(faces), np.ascontiguousarray(uv)):
        h.update(str(a.shape).encode())
        h.update(str(a.dtype).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


RIG_FILE = "rig.yaml"  # the cameras a texcoord set was made for, in the set (slide, predict with a rig, views)


def recorded_rig(texcoords: str | os.PathLike) -> Path | None:
    """The rig file a texcoord set records (``TC/rig.yaml``: written by `slide`, by `views`
    and by `predict` given a rig), or None when it records none."""
    path = Path(texcoords) / RIG_FILE
    return path if path.is_file() else None


def rig_record(rig) -> dict:
    """What a texcoord set records of the cameras it was made for: name -> width, height,
    K, R, t (`TexcoordSet.check_rig` compares a rig with it)."""
    return {cam.name: {"width": cam.width, "height": cam.height, "K": cam.K.tolist(), "R": cam.R.tolist(),
                       "t": cam.t.tolist()} for cam in rig}


def dataset_record(dataset) -> dict:
    """What a texcoord set records of the dataset it was made from (`TexcoordSet.check_dataset`
    compares a dataset with it)."""

    return {"path": str(Path(dataset.path).resolve()), "name": dataset.name, "num_poses": dataset.num_poses,
            "num_vertices": dataset.num_vertices, "mesh": fingerprint(dataset.faces, dataset.uv),
            "content": content_fingerprint(dataset)}


def _check_displacements(d: np.ndarray, source: Path) -> None:
    """Every value finite and |d| <= MAX_DISPLACEMENT, read in blocks (d may be memory-mapped)."""
    rows = max(1, (1 << 24) // max(1, d[0].nbytes)) if len(d) else 1
    for start in range(0, len(d), rows):
        block = read_rows(d, start, start + rows).astype(np.float64)
        finite = np.isfinite(block).all(axis=(1, 2))
        if not finite.all():
            raise InputError(source, f"NaN or infinite displacement (row {start + int(np.argmin(finite))})")
        norm = np.sqrt((block ** 2).sum(axis=2)).max(axis=1)
        if np.any(norm > MAX_DISPLACEMENT):
            row = int(np.argmax(norm > MAX_DISPLACEMENT))
            raise InputError(source, f"displacement of length {norm[row]:.4g} uv units at row {start + row} "
                             f"(more than {MAX_DISPLACEMENT}: not a texcoord perturbation)")


def _check_parent(parent: np.ndarray, num_vertices: int, source) -> None:
    """InputError (naming `source`) unless parent is (n',2) integers, each vertex's parents
    preceding it (the base vertices name themselves)."""
    if parent.shape != (num_vertices, 2) or not np.issubdtype(parent.dtype, np.integer):
        raise InputError(source, f"parent must be integers with shape ({num_vertices},2), got "
                         f"{parent.shape} {parent.dtype}")
    index = np.arange(len(parent))
    base = (parent[:, 0] == index) & (parent[:, 1] == index)
    if len(parent) and (parent.min() < 0 or not np.all(base | (parent.max(axis=1) < index))):
        raise InputError(source, "parent names a vertex that does not precede it")


def check_uncertainty(u: np.ndarray, shape: tuple[int, int], error: Callable[[str, int | None], Exception]) -> None:
    """The one check of a predictive uncertainty, for every writer and every reader of
    texcoord sets: (len(poses), n') float32 (`UNCERTAINTY_DTYPE`) standard deviations, every
    one finite and >= 0 (0 is an exact observation). Writers cast to float32 first and
    check what they will write: a float64 value beyond float32's range is infinite there.

    Args:
        u: the array (a memory map is read in blocks, through its file).
        shape: (len(poses), n').
        error: makes the exception of a problem ("negative uncertainty") and the row it is
            in (None for the dtype or shape): an InputError naming a file for readers, an
            OptionError naming an argument for writers of given arrays.

    Raises:
        What `error` makes.
    """
    if u.dtype != UNCERTAINTY_DTYPE:
        raise error(f"dtype {u.dtype.str if u.dtype.kind == 'f' else u.dtype}, expected float32 (little-endian "
                    "<f4) standard deviations", None)
    if u.shape != tuple(shape):
        raise error(f"shape {u.shape}, expected {tuple(shape)}", None)
    rows = max(1, (1 << 24) // max(1, u[0].nbytes)) if len(u) else 1
    for start in range(0, len(u), rows):
        block = read_rows(u, start, start + rows)
        finite = np.isfinite(block).all(axis=1)
        negative = (np.where(np.isfinite(block), block, 0.0) < 0).any(axis=1)
        if not finite.all() or negative.any():
            row = int(np.argmax(~finite | negative))
            what = "NaN or infinite" if not finite[row] else "negative"
            raise error(f"{what} uncertainty (a standard deviation is a finite number >= 0)", start + row)


def open_texcoords(path: str | os.PathLike, num_vertices: int | None = None,
                   num_poses: int | None = None) -> TexcoordSet:
    """Open a texcoord set directory and validate its header and mesh.

    Args:
        path: the directory.
        num_vertices: the dataset's vertex count, checked against the set's base mesh.
        num_poses: the dataset's pose count: every pose of the set must be below it.

    Per-camera arrays are validated (shape, dtype, finite, |d| <= MAX_DISPLACEMENT, the
    uncertainty's `check_uncertainty`) when first read.
    """
    path = as_path(path, "path")
    num_vertices = None if num_vertices is None else as_index(num_vertices, "num_vertices")
    num_poses = None if num_poses is None else as_index(num_poses, "num_poses")
    header = TexcoordHeader.read(path, num_poses)
    mesh_file = path / "mesh.npz"
    mesh = load_npz(mesh_file)
    for key in ("faces", "uv", "parent"):
        if key not in mesh:
            raise InputError(mesh_file, f"missing array '{key}'")
    validate_mesh(mesh["faces"], mesh["uv"], mesh_file)
    parent = mesh["parent"]
    _check_parent(parent, len(mesh["uv"]), mesh_file)
    tc = TexcoordSet(path=path, header=header, faces=mesh["faces"].astype(np.int32),
                     uv=mesh["uv"].astype(np.float32), parent=parent.astype(np.int32))
    if num_vertices is not None and tc.num_base_vertices != num_vertices:
        raise InputError(mesh_file, f"made for a mesh of {tc.num_base_vertices} vertices, "
                         f"the dataset has {num_vertices}")
    return tc


def as_texcoords(texcoords: "TexcoordSet | str | os.PathLike", name: str = "texcoords") -> TexcoordSet:
    """A `TexcoordSet` as is, or the texcoord set folder at a path opened (`open_texcoords`);
    OptionError naming `name` for anything else."""
    if isinstance(texcoords, TexcoordSet):
        return texcoords
    if not isinstance(texcoords, (str, os.PathLike)):
        raise OptionError(name, f"must be a TexcoordSet or a texcoord set folder path, got {type(texcoords).__name__}")
    return open_texcoords(texcoords)


def write_header(path: Path, *, faces: np.ndarray, uv: np.ndarray, parent: np.ndarray, source: str,
                 subdiv: int, poses: Sequence[int], cameras: Sequence[str], **extra: Any) -> None:
    """Write texcoords.json (`TexcoordHeader`: the header is checked first) and mesh.npz
    into an existing directory `path` (a set being built, renamed into place whole)."""
    header = TexcoordHeader(source=source, subdiv=subdiv, poses=tuple(int(p) for p in poses), cameras=tuple(cameras),
                            record=extra)
    np.savez_compressed(path / "mesh.npz", faces=np.asarray(faces, np.int32), uv=np.asarray(uv, np.float32),
                        parent=np.asarray(parent, np.int32))
    header.write(path)


@writer("save_texcoords", out="path", inputs=lambda a: (a["displacement"], a["assigned"]))
def save_texcoords(path: str | os.PathLike, *, faces: np.ndarray, uv: np.ndarray, parent: np.ndarray,
                   source: str, subdiv: int, poses: Sequence[int],
                   displacement: dict[str, np.ndarray], assigned: dict[str, np.ndarray],
                   uncertainty: dict[str, np.ndarray] | None = None, overwrite: bool = False, **extra: Any) -> Path:
    """Write a whole texcoord set atomically from in-memory arrays, under the writer policy
    (`mvtex.util.output`): an existing folder is replaced only when mvtex wrote all it holds
    (another command's output only with `overwrite`), never an input.

    Everything is checked before anything is written, with the rules `open_texcoords`
    reads by: the mesh (faces, uv, parent), subdiv in 0..MAX_SUBDIV, poses distinct
    non-negative integers, camera names, every displacement finite with |d| at most
    MAX_DISPLACEMENT uv units (the whole atlas: larger is no texcoord perturbation), and
    each uncertainty as it will be written (float32: `check_uncertainty`).

    Args:
        displacement: camera name -> (len(poses), n', 2) float32.
        assigned: camera name -> (len(poses), n') bool.
        uncertainty: optional camera name -> (len(poses), n') predictive standard deviation
            of d (cameras without one write none), written as float32: finite and >= 0 there.

    Raises:
        OptionError: an argument of the wrong type, shape or value, named.
    """
    cameras = check_texcoord_arrays(faces=faces, uv=uv, parent=parent, source=source, subdiv=subdiv, poses=poses,
                                    displacement=displacement, assigned=assigned)
    written: dict[str, np.ndarray] = {}
    if uncertainty is not None:
        if not isinstance(uncertainty, dict) or not set(uncertainty) <= set(cameras):
            raise OptionError("uncertainty", "must be a dict: camera name (of displacement) -> (len(poses), n') array")
        for cam, u in uncertainty.items():
            name = f"uncertainty[{cam!r}]"
            u = _array(u, name)
            if u.dtype.kind not in "fiu":
                raise OptionError(name, f"must be numbers, got {u.dtype}")
            with np.errstate(over="ignore", invalid="ignore"):
                written[cam] = u.astype(UNCERTAINTY_DTYPE)
            check_uncertainty(written[cam], (len(poses), len(uv)), lambda problem, row: OptionError(
                None, f"{name}: {problem}" + ("" if row is None else f" at row {row}") + " (as float32, as it is written)"))
    if not isinstance(path, (str, os.PathLike)):
        raise OptionError("path", f"must be a folder path, got {type(path).__name__}")
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.mkdir()
        write_header(tmp, faces=faces, uv=uv, parent=parent, source=source, subdiv=subdiv, poses=poses,
                     cameras=cameras, **extra)
        for cam in cameras:
            (tmp / cam).mkdir()
            np.save(tmp / cam / "displacement.npy", np.asarray(displacement[cam], np.float32), allow_pickle=False)
            np.save(tmp / cam / "assigned.npy", np.asarray(assigned[cam], bool), allow_pickle=False)
            if cam in written:
                np.save(tmp / cam / "uncertainty.npy", written[cam], allow_pickle=False)
    return path


def _array(value, name: str, dtype=None) -> np.ndarray:
    if value is None or isinstance(value, (str, bytes, dict)):
        raise OptionError(name, f"must be an array, got {type(value).__name__}")
    try:
        return np.asarray(value) if dtype is None else np.asarray(value, dtype=dtype)
    except (TypeError, ValueError, OverflowError):
        raise OptionError(name, f"must be an array of numbers, got {type(value).__name__}") from None


def check_texcoord_arrays(*, faces, uv, parent, source, subdiv, poses, displacement, assigned) -> list[str]:
    """Check what `save_texcoords` is given, by the rules `open_texcoords` reads a set by.

    Returns:
        The camera names (the keys of `displacement`).

    Raises:
        OptionError: naming the argument ("displacement['left']: ...").
    """
    def named(name: str, check, *args) -> None:
        try:
            check(*args)
        except InputError as err:
            raise OptionError(None, f"{name}: {err.problem}") from None

    faces, uv, parent = _array(faces, "faces"), _array(uv, "uv"), _array(parent, "parent")
    named("faces/uv", validate_mesh, faces, uv, None)
    named("parent", _check_parent, parent, len(uv), None)
    if isinstance(poses, (str, bytes)) or not hasattr(poses, "__len__"):
        raise OptionError("poses", f"must be a list of pose indices, got {type(poses).__name__}")
    if not isinstance(displacement, dict) or not displacement:
        raise OptionError("displacement", "must be a non-empty dict: camera name -> (len(poses), n', 2) array")
    if not isinstance(assigned, dict) or set(assigned) != set(displacement):
        raise OptionError("assigned", "must be a dict with the cameras of displacement: camera name -> "
                          "(len(poses), n') bool array")
    cameras = list(displacement)
    for cam in cameras:
        check_camera_name(cam)
    if len({c.lower() for c in cameras}) != len(cameras):
        raise OptionError("displacement", "names a camera twice (ignoring case)")
    TexcoordHeader(source=source, subdiv=subdiv, poses=tuple(poses), cameras=tuple(cameras))  # OptionError naming it
    shape = (len(poses), len(uv))
    for cam in cameras:
        d = _array(displacement[cam], f"displacement[{cam!r}]")
        a = _array(assigned[cam], f"assigned[{cam!r}]")
        if d.shape != shape + (2,) or d.dtype.kind not in "fiu":
            raise OptionError(None, f"displacement[{cam!r}] must be numbers with shape {shape + (2,)}, got {d.shape} {d.dtype}")
        if a.shape != shape or a.dtype != np.bool_:
            raise OptionError(None, f"assigned[{cam!r}] must be bool with shape {shape}, got {a.shape} {a.dtype}")
        named(f"displacement[{cam!r}]", _check_displacements, d.astype(np.float32), None)
    return cameras
