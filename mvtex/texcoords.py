"""The texcoord set (DESIGN §4): the hub format that slide, predict and views write and
eval, triangulate, render, views and preview read.

    texcoords.json   {"format": "mvtex-texcoords", "version": 1, "source": "ts"|"tsnn"|...,
                      "subdiv": s, "poses": [...], "cameras": [...], ...}
    mesh.npz         faces int32 (m',3), uv float32 (n',2) (T_G on the subdivided mesh),
                     parent int32 (n',2)
    <camera>/displacement.npy  float32 (len(poses), n', 2): d = T_N - T_G
    <camera>/assigned.npy      bool (len(poses), n')
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .errors import InputError
from .io import atomic_path, load_npy, load_npz, read_header
from .mesh import apply_extension, extension_matrix

FORMAT = "mvtex-texcoords"
VERSION = 1


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
            self._cache[camera] = (d, a)
        return self._cache[camera]

    def displacement(self, camera: str, pose: int) -> np.ndarray:
        """d = T_N - T_G, (n',2) float32, for a dataset pose index."""
        return np.asarray(self._arrays(camera)[0][self.row(pose)])

    def assigned(self, camera: str, pose: int) -> np.ndarray:
        """(n',) bool: True where d came from the ray."""
        return np.asarray(self._arrays(camera)[1][self.row(pose)])

    def texcoords(self, camera: str, pose: int) -> np.ndarray:
        """T_N = T_G + d, (n',2) float32."""
        return self.uv + self.displacement(camera, pose)

    def positions(self, positions: np.ndarray) -> np.ndarray:
        """Extend base-mesh positions (n,3) (or (K,n,3)) to this set's subdivided mesh."""
        if ("extension",) not in self._cache:  # camera names are strings: no clash
            self._cache[("extension",)] = extension_matrix(self.parent)
        return apply_extension(self._cache[("extension",)], positions)


def open_texcoords(path: str | os.PathLike, num_vertices: int | None = None) -> TexcoordSet:
    """Open a texcoord set directory; `num_vertices` checks it against a dataset's mesh."""
    path = Path(path)
    meta = read_header(path, "texcoords.json", FORMAT, VERSION, "a texcoord set")
    for key in ("poses", "cameras"):
        if not isinstance(meta.get(key), list):
            raise InputError(path / "texcoords.json", f"missing list '{key}'")
    mesh = load_npz(path / "mesh.npz")
    for key in ("faces", "uv", "parent"):
        if key not in mesh:
            raise InputError(path / "mesh.npz", f"missing array '{key}'")
    tc = TexcoordSet(path=path, meta=meta, faces=mesh["faces"].astype(np.int32), uv=mesh["uv"].astype(np.float32),
                     parent=mesh["parent"].astype(np.int32))
    if num_vertices is not None and tc.num_base_vertices != num_vertices:
        raise InputError(path / "mesh.npz", f"made for a mesh of {tc.num_base_vertices} vertices, "
                         f"the dataset has {num_vertices}")
    return tc


def write_header(path: Path, *, faces: np.ndarray, uv: np.ndarray, parent: np.ndarray, source: str,
                 subdiv: int, poses: Sequence[int], cameras: Sequence[str], **extra: Any) -> None:
    """Write texcoords.json and mesh.npz into an existing directory `path`."""
    np.savez_compressed(path / "mesh.npz", faces=np.asarray(faces, np.int32), uv=np.asarray(uv, np.float32),
                        parent=np.asarray(parent, np.int32))
    meta = {"format": FORMAT, "version": VERSION, "source": source, "subdiv": int(subdiv),
            "poses": [int(p) for p in poses], "cameras": list(cameras), **extra}
    (path / "texcoords.json").write_text(json.dumps(meta, indent=2) + "\n")


def save_texcoords(path: str | os.PathLike, *, faces: np.ndarray, uv: np.ndarray, parent: np.ndarray,
                   source: str, subdiv: int, poses: Sequence[int],
                   displacement: dict[str, np.ndarray], assigned: dict[str, np.ndarray], **extra: Any) -> Path:
    """Write a whole texcoord set atomically from in-memory arrays.

    Args:
        displacement: camera name -> (len(poses), n', 2) float32.
        assigned: camera name -> (len(poses), n') bool.
    """
    path = Path(path)
    cameras = list(displacement)
    with atomic_path(path) as tmp:
        tmp.mkdir()
        write_header(tmp, faces=faces, uv=uv, parent=parent, source=source, subdiv=subdiv, poses=poses,
                     cameras=cameras, **extra)
        for cam in cameras:
            (tmp / cam).mkdir()
            np.save(tmp / cam / "displacement.npy", np.asarray(displacement[cam], np.float32), allow_pickle=False)
            np.save(tmp / cam / "assigned.npy", np.asarray(assigned[cam], bool), allow_pickle=False)
    return path
