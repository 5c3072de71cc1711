"""Mesh topology against independent computations (trimesh, plain loops)."""

from __future__ import annotations

import numpy as np
from helpers import grid_mesh, wave

from mvtex.data.mesh import apply_extension, apply_parent, extension_matrix, face_neighbours, rms_distance, subdivide


def test_face_neighbours_match_trimesh_face_adjacency():
    import trimesh

    faces, _, rest = grid_mesh(7, 5)
    nb = face_neighbours(faces)
    mesh = trimesh.Trimesh(rest, faces, process=False)
    expected = {tuple(sorted(p)) for p in mesh.face_adjacency.tolist()}
    found = {tuple(sorted((f, int(g)))) for f in range(len(faces)) for g in nb[f] if g >= 0}
    assert found == expected
    # Neighbour k of face f shares the edge (k, k+1) of f.
    for f in range(len(faces)):
        for k in range(3):
            if nb[f, k] >= 0:
                assert {faces[f, k], faces[f, (k + 1) % 3]} <= set(faces[nb[f, k]].tolist())


def test_extension_matrix_gives_recursive_midpoints():
    faces, uv, rest = grid_mesh(6, 5)
    positions = wave(rest, 0.02, 0.3)
    for levels in (1, 2):
        sub = subdivide(faces, len(rest), levels)
        expected = list(positions)
        for a, b in sub.parent[len(rest):]:  # parents precede children: a plain loop
            expected.append(0.5 * (expected[a] + expected[b]))
        expected = np.array(expected)
        E = extension_matrix(sub.parent)
        assert E.shape == (len(sub.parent), len(rest))
        assert np.allclose(apply_extension(E, positions), expected, atol=1e-15)
        assert np.allclose(sub.apply(positions), expected, atol=1e-15)
        batch = np.stack([positions, 2 * positions])
        assert np.allclose(apply_parent(batch, sub.parent)[1], 2 * expected, atol=1e-15)
        assert apply_parent(positions.astype(np.float32), sub.parent).dtype == np.float32


def test_rms_distance():
    a = np.zeros((4, 3))
    b = np.array([[3.0, 4, 0], [0, 0, 0], [0, 0, 1], [1, 0, 0]])
    assert rms_distance(a, b) == np.sqrt((25 + 0 + 1 + 1) / 4)
    assert rms_distance(a, b, np.array([True, False, False, False])) == 5.0
    assert rms_distance(a, b, np.zeros(4, bool)) is None
