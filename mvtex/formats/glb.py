"""GLB export (trimesh) of meshes side by side, for the report's 3-D view.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np


def export_glb(path: str | os.PathLike, meshes: Sequence[tuple[str, np.ndarray, np.ndarray, np.ndarray]],
               spacing: float = 1.25, body: tuple[np.ndarray, np.ndarray, Sequence[int]] | None = None) -> Path:
    """Write meshes side by side (along x, in order) into one GLB, atomically.

    Args:
        meshes: (name, positions (n,3) m, faces (m,3) int, vertex colours (n,3) uint8).
        spacing: distance between neighbours, in units of the widest mesh's x extent.
        body: optional (positions (nb,3), faces (mb,3), rgb) of the wearer, drawn in one
            colour inside every mesh (moved with it), so that each is seen worn.

    Positions are kept in world axes, only centred: the built-in data is y-up with the
    cameras on +z, glTF's convention, so a viewer opens on the garment's front.
    """
    import trimesh

    from mvtex.util.output import atomic_path

    width = max(float(np.ptp(np.asarray(p)[:, 0])) for _, p, _, _ in meshes)
    scene = trimesh.Scene()
    for i, (name, positions, faces, colors) in enumerate(meshes):
        p = np.asarray(positions, np.float64)
        p = p - p.mean(axis=0)
        p[:, 0] += (i - (len(meshes) - 1) / 2) * spacing * width
        rgba = np.hstack([np.asarray(colors, np.uint8), np.full((len(p), 1), 255, np.uint8)])
        mesh = trimesh.Trimesh(vertices=p, faces=np.asarray(faces, np.int64), vertex_colors=rgba, process=False)
        scene.add_geometry(mesh, node_name=name, geom_name=name)
        if body is not None:
            shift = p[0] - np.asarray(positions, np.float64)[0]
            b = np.asarray(body[0], np.float64) + shift
            colour = np.tile(np.append(np.asarray(body[2], np.uint8), 255), (len(b), 1))
            worn = trimesh.Trimesh(vertices=b, faces=np.asarray(body[1], np.int64), vertex_colors=colour, process=False)
            scene.add_geometry(worn, node_name=f"{name}_body", geom_name=f"{name}_body")
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(scene.export(file_type="glb"))
    return path
