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
                               report one; readers that do not know it ignore it
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from mvtex.data.mesh import apply_extension, extension_matrix
from mvtex.data.limits import MAX_SUBDIV
from mvtex.util.errors import InputError, OptionError
from mvtex.util.files import load_npy, load_npz, read_header, read_row, read_rows
from mvtex.util.output import atomic_path, writer

FORMAT = "mvtex-texcoords"

_LAYOUT = ["texcoords.json", "mesh.npz", "rig.yaml"]  # the files of a set beside its camera folders


VERSION = 1




MAX_DISPLACEMENT = 1.0


"""Largest |d| accepted in a set (uv units: the whole atlas is 1 wide); larger is corrupt."""


@dataclass(frozen=True)
class TexcoordSet:
    """An opened texcoord set; per-camera arrays are memory-mapped on first access.

    Attributes:
        path: the directory. meta: texcoords.json as a dict.
        faces: (m',3) int32. uv: (n',2) float32 T_G on the (subdivided) mesh. parent: (n',2) int32.
    """

    path: Path
    meta: dict[str, Any]
    faces: np.ndarray
    uv: np.ndarray
    parent: np.ndarray
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def poses(self) -> list[int]:
        return [int(p) for p in self.meta["poses"]]

    @property
    def cameras(self) -> list[str]:
        return [str(c) for c in self.meta["cameras"]]

    @property
    def subdiv(self) -> int:
        return int(self.meta.get("subdiv", 0))

    @property
    def source(self) -> str:
        return str(self.meta.get("source", "unknown"))

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
            self._cache[camera] = (d, a)
        return self._cache[camera]

    # Rows are read through the files (`read_rows`), not the maps: pages read through a map
    # stay resident while it lives, so a pass over a 10,000-pose set would hold all of it.
    def displacement(self, camera: str, pose: int) -> np.ndarray:
        """d = T_N - T_G, (n',2) float32, for a dataset pose index (a copy)."""
        return read_row(self._arrays(camera)[0], self.row(pose))

    def assigned(self, camera: str, pose: int) -> np.ndarray:
        """(n',) bool: True where d came from the ray (a copy)."""
        return read_row(self._arrays(camera)[1], self.row(pose))

    def _uncertainty(self, camera: str) -> np.ndarray | None:
        key = ("uncertainty", camera)
        if key not in self._cache:
            self._arrays(camera)  # the camera exists and its displacements are sound
            file = self.path / camera / "uncertainty.npy"
            u = None
            if file.is_file():
                u = load_npy(file)
                shape = (len(self.poses), len(self.uv))
                if u.shape != shape or u.dtype.kind != "f":
                    raise InputError(file, f"shape {u.shape} {u.dtype}, expected {shape} float32")
                _check_uncertainty(u, file)
            self._cache[key] = u
        return self._cache[key]

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
        from mvtex.util.fingerprint import fingerprint

        return fingerprint(*self._arrays(camera))

    def texcoords(self, camera: str, pose: int) -> np.ndarray:
        """T_N = T_G + d, (n',2) float32."""
        return self.uv + self.displacement(camera, pose)

    def check_dataset(self, dataset) -> None:
        """Refuse (InputError) a dataset other than the one this set was made from: its mesh
        (vertex count, and the fingerprint of faces and uv where recorded) and its content
        (`mvtex.data.dataset.content_fingerprint`, where recorded)."""
        from mvtex.data.dataset import content_fingerprint
        from mvtex.util.fingerprint import fingerprint

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
    import hashlib

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
    from mvtex.data.dataset import content_fingerprint
    from mvtex.util.fingerprint import fingerprint

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


def _check_uncertainty(u: np.ndarray, source: Path) -> None:
    """Every value finite and >= 0, read in blocks."""
    rows = max(1, (1 << 24) // max(1, u[0].nbytes)) if len(u) else 1
    for start in range(0, len(u), rows):
        block = read_rows(u, start, start + rows)
        ok = np.isfinite(block).all(axis=1) & (block >= 0).all(axis=1)
        if not ok.all():
            raise InputError(source, f"negative, NaN or infinite uncertainty (row {start + int(np.argmin(ok))})")


def _int_list(meta: dict, key: str, source: Path) -> list:
    values = meta.get(key)
    if not isinstance(values, list):
        raise InputError(source, f"missing list '{key}'")
    return values


def open_texcoords(path: str | os.PathLike, num_vertices: int | None = None,
                   num_poses: int | None = None) -> TexcoordSet:
    """Open a texcoord set directory and validate its header and mesh.

    Args:
        path: the directory.
        num_vertices: the dataset's vertex count, checked against the set's base mesh.
        num_poses: the dataset's pose count: every pose of the set must be below it.

    Per-camera arrays are validated (shape, dtype, finite, |d| <= MAX_DISPLACEMENT) when
    first read.
    """
    from mvtex.data.camera import check_camera_name
    from mvtex.data.dataset import validate_mesh
    from mvtex.util.checks import as_index, as_path

    path = as_path(path, "path")
    num_vertices = None if num_vertices is None else as_index(num_vertices, "num_vertices")
    num_poses = None if num_poses is None else as_index(num_poses, "num_poses")
    header = path / "texcoords.json"
    meta = read_header(path, "texcoords.json", FORMAT, VERSION, "a texcoord set")
    poses = _int_list(meta, "poses", header)
    if not poses:
        raise InputError(header, "'poses' is empty")
    if not all(isinstance(p, int) and not isinstance(p, bool) for p in poses):
        raise InputError(header, "'poses' must be a list of integer pose indices")
    bad = [p for p in poses if p < 0 or (num_poses is not None and p >= num_poses)]
    if bad:
        limit = f"[0, {num_poses})" if num_poses is not None else "non-negative"
        raise InputError(header, f"pose index {bad[0]} out of range ({limit})")
    if len(set(poses)) != len(poses):
        raise InputError(header, "'poses' lists a pose twice")
    cameras = _int_list(meta, "cameras", header)
    if not cameras:
        raise InputError(header, "'cameras' is empty")
    try:
        for name in cameras:
            check_camera_name(name)
    except ValueError as err:
        raise InputError(header, str(err)) from None
    if len({c.lower() for c in cameras}) != len(cameras):
        raise InputError(header, "'cameras' names a camera twice")
    subdiv = meta.get("subdiv", 0)
    if not isinstance(subdiv, int) or isinstance(subdiv, bool) or not 0 <= subdiv <= MAX_SUBDIV:
        raise InputError(header, f"'subdiv' must be an integer in 0..{MAX_SUBDIV}, got {subdiv!r}")
    mesh_file = path / "mesh.npz"
    mesh = load_npz(mesh_file)
    for key in ("faces", "uv", "parent"):
        if key not in mesh:
            raise InputError(mesh_file, f"missing array '{key}'")
    validate_mesh(mesh["faces"], mesh["uv"], mesh_file)
    parent = mesh["parent"]
    _check_parent(parent, len(mesh["uv"]), mesh_file)
    tc = TexcoordSet(path=path, meta=meta, faces=mesh["faces"].astype(np.int32), uv=mesh["uv"].astype(np.float32),
                     parent=parent.astype(np.int32))
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
    """Write texcoords.json and mesh.npz into an existing directory `path`."""
    np.savez_compressed(path / "mesh.npz", faces=np.asarray(faces, np.int32), uv=np.asarray(uv, np.float32),
                        parent=np.asarray(parent, np.int32))
    meta = {"format": FORMAT, "version": VERSION, "source": source, "subdiv": int(subdiv),
            "poses": [int(p) for p in poses], "cameras": list(cameras), **extra}
    (path / "texcoords.json").write_text(json.dumps(meta, indent=2) + "\n")


class PartialSet:
    """A texcoord set written row by row into ``OUT.partial`` and renamed to OUT when every
    row is in: the resumable writer of `slide` and `views`.

    Opening keeps an unfinished set of the same run (its texcoords.json holds the same poses,
    cameras, subdiv and `record` values) and continues from its done masks; another run's
    is deleted and started over (said on stderr); a folder that is not an unfinished set of
    this command is refused. Rows go through the files (positioned writes, then fsync), so
    they are on disk before a camera's done mask (``<camera>/done.npy``) says so; a kill
    loses at most the rows in flight.

    Args:
        out: the finished set's directory.
        command: the command writing it, for messages ("slide").
        source_prefix: how the set's "source" starts ("ts", "views-"): what an unfinished set
            of this command looks like.
        faces, uv, parent, source, subdiv, poses, cameras: the set's header (`write_header`).
        record: the other keys of texcoords.json, compared with an unfinished set's
            (JSON-like values: lists, not tuples).

    Raises:
        InputError: OUT.partial exists and is not an unfinished set of `command`, or its
            arrays do not have the set's shapes.
    """

    def __init__(self, out: str | os.PathLike, command: str, source_prefix: str, *, faces: np.ndarray,
                 uv: np.ndarray, parent: np.ndarray, source: str, subdiv: int, poses: Sequence[int],
                 cameras: Sequence[str], record: dict[str, Any]):
        from mvtex.util.files import load_npy
        from mvtex.util.output import remove_leftovers

        self.out = Path(out)
        self.path = self.out.with_name(self.out.name + ".partial")
        self.poses = [int(p) for p in poses]
        self.cameras = list(cameras)
        self._open(command, source_prefix, faces=faces, uv=uv, parent=parent, source=source, subdiv=subdiv,
                   record=record)
        shape = (len(self.poses), len(uv))
        self.done: dict[str, np.ndarray] = {}
        for cam in self.cameras:
            # A run killed while saving a done mask leaves the mask's hidden temporary and aside
            # copies: they must not end up in the finished set. No mask (a run stopped while
            # finishing): that camera is done again.
            remove_leftovers(self.path / cam, "done.npy")
            mask = self.path / cam / "done.npy"
            self.done[cam] = np.array(load_npy(mask, mmap=False), dtype=bool) if mask.is_file() else np.zeros(shape[0], bool)
            d, a = (load_npy(self.path / cam / name) for name in ("displacement.npy", "assigned.npy"))
            if d.shape != shape + (2,) or a.shape != shape or self.done[cam].shape != shape[:1]:
                raise InputError(self.path / cam, "unfinished result has unexpected array shapes; delete it and rerun")
            del d, a

    def _open(self, command: str, source_prefix: str, *, faces, uv, parent, source, subdiv, record) -> None:
        import shutil
        import sys

        from mvtex.util.files import create_npy, read_json
        from mvtex.util.output import foreign_entries, mark_output, written_by_mvtex

        partial = self.path
        if partial.is_dir():
            try:
                old = read_json(partial / "texcoords.json")
            except InputError:
                old = None
            if not (isinstance(old, dict) and old.get("format") == FORMAT
                    and str(old.get("source", "")).startswith(source_prefix)):
                raise InputError(partial, f"exists and is not an unfinished mvtex {command}; move it away and rerun")
            if all(old.get(k) == v for k, v in record.items()) and old.get("poses") == self.poses \
                    and old.get("cameras") == self.cameras and old.get("subdiv") == subdiv:
                return
            # Only what mvtex wrote there goes: its manifest's entries (and the views' rig.yaml,
            # saved last), or, for a partial from before manifests, the set's own layout.
            if written_by_mvtex(partial) is not None:
                foreign = [e for e in foreign_entries(partial) if e != "rig.yaml"]
            else:
                layout = [str(c) for c in old.get("cameras") or []] + _LAYOUT
                foreign = [e for e in foreign_entries(partial) if e.split("/")[0] not in layout]
            if foreign:
                raise InputError(partial, f"an unfinished run with other settings that also holds files mvtex did "
                                 f"not write ({', '.join(foreign[:3])}); move them away and rerun")
            print(f"{partial}: an unfinished run with other settings; starting over", file=sys.stderr)
            shutil.rmtree(partial)
        # Built in a stamped temporary beside it, marked as `command`'s, renamed in whole.
        with atomic_path(partial) as tmp:
            tmp.mkdir()
            write_header(tmp, faces=faces, uv=uv, parent=parent, source=source, subdiv=subdiv, poses=self.poses,
                         cameras=self.cameras, **record)
            for cam in self.cameras:
                (tmp / cam).mkdir()
                create_npy(tmp / cam / "displacement.npy", np.float32, (len(self.poses), len(uv), 2))
                create_npy(tmp / cam / "assigned.npy", np.bool_, (len(self.poses), len(uv)))
                np.save(tmp / cam / "done.npy", np.zeros(len(self.poses), bool), allow_pickle=False)
            mark_output(tmp, command)

    @property
    def rows_done(self) -> int:
        """(pose, camera) rows already in."""
        return int(sum(mask.sum() for mask in self.done.values()))

    def todo(self, camera: str) -> list[int]:
        """Rows (indices into `poses`) of `camera` still to compute."""
        return np.flatnonzero(~self.done[camera]).tolist()

    def write(self, camera: str, rows: Sequence[int], displacement: np.ndarray, assigned: np.ndarray) -> None:
        """Write rows of one camera ((r,n',2) float32 and (r,n') bool), then mark them done."""
        from mvtex.util.files import save_npy, write_npy_rows

        rows = list(rows)
        write_npy_rows(self.path / camera / "displacement.npy", rows, displacement)
        write_npy_rows(self.path / camera / "assigned.npy", rows, assigned)
        self.done[camera][rows] = True
        save_npy(self.path / camera / "done.npy", self.done[camera])

    def finish(self) -> Path:
        """Rename the finished set to OUT (an older OUT aside first, deleted after), then drop
        the done masks: a stop in between leaves a resumable partial or a complete set.

        Raises:
            RuntimeError: rows still missing (a backend that lost tasks): never rename an
                incomplete set into place.
        """
        from mvtex.util.output import forget, replace_path

        missing = [c for c in self.cameras if not self.done[c].all()]
        if missing:
            raise RuntimeError(f"{self.path}: {int((~self.done[missing[0]]).sum())} poses of camera {missing[0]!r} "
                               "were not computed; rerun to finish them")
        replace_path(self.path, self.out)
        for cam in self.cameras:
            (self.out / cam / "done.npy").unlink(missing_ok=True)
        forget(self.out, [f"{cam}/done.npy" for cam in self.cameras])
        return self.out


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
    non-negative integers, camera names, and every displacement finite with |d| at most
    MAX_DISPLACEMENT uv units (the whole atlas: larger is no texcoord perturbation).

    Args:
        displacement: camera name -> (len(poses), n', 2) float32.
        assigned: camera name -> (len(poses), n') bool.
        uncertainty: optional camera name -> (len(poses), n') float32 predictive standard
            deviation of d (cameras without one write none); finite and >= 0.

    Raises:
        OptionError: an argument of the wrong type, shape or value, named.
    """
    cameras = check_texcoord_arrays(faces=faces, uv=uv, parent=parent, source=source, subdiv=subdiv, poses=poses,
                                    displacement=displacement, assigned=assigned)
    if uncertainty is not None:
        if not isinstance(uncertainty, dict) or not set(uncertainty) <= set(cameras):
            raise OptionError("uncertainty", "must be a dict: camera name (of displacement) -> (len(poses), n') array")
        for cam, u in uncertainty.items():
            u = _array(u, f"uncertainty[{cam!r}]")
            if u.shape != (len(poses), len(uv)) or u.dtype.kind not in "fiu" or not np.isfinite(u).all() or (u < 0).any():
                raise OptionError(None, f"uncertainty[{cam!r}] must be finite numbers >= 0 with shape {(len(poses), len(uv))}")
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
            if uncertainty is not None and cam in uncertainty:
                np.save(tmp / cam / "uncertainty.npy", np.asarray(uncertainty[cam], np.float32), allow_pickle=False)
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
    from mvtex.data.camera import check_camera_name
    from mvtex.data.dataset import validate_mesh

    def named(name: str, check, *args) -> None:
        try:
            check(*args)
        except InputError as err:
            raise OptionError(None, f"{name}: {err.problem}") from None

    faces, uv, parent = _array(faces, "faces"), _array(uv, "uv"), _array(parent, "parent")
    named("faces/uv", validate_mesh, faces, uv, None)
    named("parent", _check_parent, parent, len(uv), None)
    if not isinstance(source, str) or not source:
        raise OptionError("source", f"must be a non-empty string (\"ts\", \"tsnn\", ...), got {source!r}")
    if isinstance(subdiv, bool) or not isinstance(subdiv, (int, np.integer)) or not 0 <= subdiv <= MAX_SUBDIV:
        raise OptionError("subdiv", f"must be an integer in 0..{MAX_SUBDIV}, got {subdiv!r}")
    if isinstance(poses, (str, bytes)) or not hasattr(poses, "__len__"):
        raise OptionError("poses", f"must be a list of pose indices, got {type(poses).__name__}")
    if not len(poses) or not all(isinstance(p, (int, np.integer)) and not isinstance(p, bool) and p >= 0
                                 for p in poses):
        raise OptionError("poses", f"must be a non-empty list of non-negative integer pose indices, got {poses!r}")
    if len(set(int(p) for p in poses)) != len(poses):
        raise OptionError("poses", "lists a pose twice")
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
