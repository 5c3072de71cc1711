"""PLY export: binary little-endian triangle meshes with per-vertex texture coordinates,
colours and extra scalar properties (trimesh, MeshLab and COLMAP's GUI read them).

    element vertex n:  float x y z, [float s t], [uchar red green blue], [extra properties]
    element face m:    list uchar int vertex_indices

`s, t` is the texture coordinate (u right, v up), the names trimesh and MeshLab expect.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mvtex.util.output import atomic_path

# numpy dtype -> PLY scalar type name.
_PLY_TYPES = {
    np.dtype("int8"): "char", np.dtype("uint8"): "uchar", np.dtype("int16"): "short",
    np.dtype("uint16"): "ushort", np.dtype("int32"): "int", np.dtype("uint32"): "uint",
    np.dtype("float32"): "float", np.dtype("float64"): "double",
}


def write_ply(path: str | os.PathLike, positions: np.ndarray, faces: np.ndarray, *, uv: np.ndarray | None = None,
              colors: np.ndarray | None = None, vertex_properties: dict[str, np.ndarray] | None = None,
              comments: tuple[str, ...] = ()) -> Path:
    """Write a triangle mesh as a binary little-endian PLY, atomically.

    Args:
        path: output file.
        positions: (n,3) vertex positions (written as float32).
        faces: (m,3) int vertex indices (written as int32 lists of length 3).
        uv: optional (n,2) texture coordinates, written as float32 properties `s`, `t`.
        colors: optional (n,3) uint8 RGB, written as `red`, `green`, `blue`.
        vertex_properties: optional extra per-vertex scalars name -> (n,) array of any
            numeric dtype in `_PLY_TYPES` (bool is written as uchar).
        comments: header comment lines.

    Returns:
        The path written.
    """
    positions = np.asarray(positions)
    faces = np.asarray(faces)
    n = len(positions)
    if positions.shape != (n, 3):
        raise ValueError(f"positions must be (n,3), got {positions.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must be (m,3), got {faces.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= n):
        raise ValueError(f"faces index vertices outside [0, {n})")
    columns: list[tuple[str, np.ndarray]] = [(k, positions[:, i].astype(np.float32)) for i, k in enumerate("xyz")]
    if uv is not None:
        uv = np.asarray(uv)
        if uv.shape != (n, 2):
            raise ValueError(f"uv must be ({n},2), got {uv.shape}")
        columns += [("s", uv[:, 0].astype(np.float32)), ("t", uv[:, 1].astype(np.float32))]
    if colors is not None:
        colors = np.asarray(colors)
        if colors.shape != (n, 3) or colors.dtype != np.uint8:
            raise ValueError(f"colors must be ({n},3) uint8, got {colors.shape} {colors.dtype}")
        columns += [(k, colors[:, i]) for i, k in enumerate(("red", "green", "blue"))]
    for name, values in (vertex_properties or {}).items():
        values = np.asarray(values)
        if values.dtype == np.bool_:
            values = values.astype(np.uint8)
        if values.shape != (n,) or values.dtype not in _PLY_TYPES:
            raise ValueError(f"vertex property {name!r} must be ({n},) numeric, got {values.shape} {values.dtype}")
        columns.append((name, values))

    vertex_dtype = np.dtype([(name, values.dtype.newbyteorder("<")) for name, values in columns])
    vertices = np.empty(n, dtype=vertex_dtype)
    for name, values in columns:
        vertices[name] = values
    face_dtype = np.dtype([("count", "u1"), ("indices", "<i4", (3,))])
    face_rows = np.empty(len(faces), dtype=face_dtype)
    face_rows["count"] = 3
    face_rows["indices"] = faces

    header = ["ply", "format binary_little_endian 1.0", *(f"comment {c}" for c in comments),
              f"element vertex {n}",
              *(f"property {_PLY_TYPES[values.dtype]} {name}" for name, values in columns),
              f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            f.write(vertices.tobytes())
            f.write(face_rows.tobytes())
    return path
