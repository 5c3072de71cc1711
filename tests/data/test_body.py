"""The body in the dataset format (body.npz + body.npy, DESIGN §4) and in the importer:
round trips against closed-form meshes, every malformed file refused with one line naming it."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from helpers import grid_mesh, one_line_error, run, wave, write_obj

from mvtex.data.dataset import load_dataset, save_dataset
from mvtex.util.errors import InputError


def octahedron(radius: float, centre) -> tuple[np.ndarray, np.ndarray]:
    """A closed octahedron, faces counter-clockwise seen from outside: (faces (8,3), vertices (6,3))."""
    v = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64)
    faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]],
                     dtype=np.int32)
    return faces, radius * v + np.asarray(centre, dtype=np.float64)


def _body_sequence(num_poses: int) -> tuple[np.ndarray, np.ndarray]:
    """The octahedron moving along z and growing, pose by pose: (faces, (K,6,3))."""
    faces, _ = octahedron(1.0, (0, 0, 0))
    return faces, np.stack([octahedron(0.1 + 0.01 * k, (0.0, 0.0, -0.2 - 0.01 * k))[1] for k in range(num_poses)])


@pytest.fixture(scope="module")
def bodied(tmp_path_factory):
    """The wavy sheet (6 poses) with an octahedron body behind it."""
    faces, uv, rest = grid_mesh()
    phases = np.linspace(0, 2.5, 6)
    gt = np.stack([wave(rest, 0.015, p) for p in phases])
    inferred = np.stack([wave(rest, 0.004, p) for p in phases])
    body_faces, body = _body_sequence(6)
    path = tmp_path_factory.mktemp("body") / "sheet"
    save_dataset(path, faces=faces, uv=uv, gt=gt, inferred=inferred, poses=phases[:, None], name="sheet", rest=rest,
                 body_faces=body_faces, body=body)
    return path, body_faces, body


def test_body_round_trip(bodied):
    path, body_faces, body = bodied
    ds = load_dataset(path)
    assert ds.body is not None
    assert isinstance(ds.body.positions, np.memmap) and ds.body.positions.dtype == np.float32
    assert ds.body.positions.shape == (6, 6, 3) and ds.body.num_vertices == 6
    assert ds.body.faces.dtype == np.int32 and np.array_equal(ds.body.faces, body_faces)
    for k in (0, 5):
        pose = ds.body.pose(k)
        assert pose.dtype == np.float64 and type(pose) is np.ndarray
        np.testing.assert_array_equal(pose, body[k].astype(np.float32).astype(np.float64))
    meta = json.loads((path / "dataset.json").read_text())
    assert meta["body"] == {"num_vertices": 6, "num_faces": 8}
    # Outward faces: the signed volume of a closed CCW-outside mesh is positive.
    p = ds.body.pose(2)
    tri = p[ds.body.faces]
    assert np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() > 0


def test_dataset_without_body_loads_as_before(tiny_dataset):
    ds = load_dataset(tiny_dataset)
    assert ds.body is None and ds.body_arrays() == ()
    assert not (tiny_dataset / "body.npz").exists()
    assert "body" not in json.loads((tiny_dataset / "dataset.json").read_text())


def test_dataset_json_body_record_is_optional(bodied, tmp_path):
    path = tmp_path / "d"
    shutil.copytree(bodied[0], path)
    meta = json.loads((path / "dataset.json").read_text())
    del meta["body"]
    (path / "dataset.json").write_text(json.dumps(meta))
    assert load_dataset(path).body.num_vertices == 6
    meta["body"] = {"num_vertices": 7, "num_faces": 8}
    (path / "dataset.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="dataset.json: body num_vertices is 7"):
        load_dataset(path)


def _npz_faces(path, faces):
    np.savez(path / "body.npz", faces=faces)


MALFORMED = {
    "npz missing": (lambda p: (p / "body.npz").unlink(), "body.npz", "file not found"),
    "npy missing": (lambda p: (p / "body.npy").unlink(), "body.npy", "file not found"),
    "bad shape": (lambda p: np.save(p / "body.npy", np.zeros((6, 6, 2), np.float32)), "body.npy", "(K,nb,3)"),
    "wrong K": (lambda p: np.save(p / "body.npy", np.zeros((5, 6, 3), np.float32)), "body.npy", "pose count 5"),
    "float64": (lambda p: np.save(p / "body.npy", np.zeros((6, 6, 3))), "body.npy", "float32"),
    "nan in one pose": (lambda p: np.save(p / "body.npy", np.where(np.arange(6)[:, None, None] == 4, np.nan,
                                                                   np.load(p / "body.npy"))), "body.npy", "pose 4"),
    "beyond any rig": (lambda p: np.save(p / "body.npy", np.where(np.arange(6)[:, None, None] == 2, np.float32(3e38),
                                                                 np.load(p / "body.npy"))), "body.npy", "pose 2"),
    "face out of range": (lambda p: _npz_faces(p, np.array([[0, 1, 6]], np.int32)), "body.npz", "out of range"),
    "faces not triangles": (lambda p: _npz_faces(p, np.zeros((3, 4), np.int32)), "body.npz", "(mb,3)"),
    "float faces": (lambda p: _npz_faces(p, np.zeros((3, 3), np.float32)), "body.npz", "integers"),
    "no faces array": (lambda p: np.savez(p / "body.npz", other=np.zeros(3)), "body.npz", "missing array"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_body_is_refused_naming_the_file(bodied, tmp_path, capsys, case):
    mutate, file, problem = MALFORMED[case]
    path = tmp_path / "bad"
    shutil.copytree(bodied[0], path)
    mutate(path)
    with pytest.raises(InputError) as err:
        load_dataset(path)
    message = str(err.value)
    assert str(path / file) in message and problem in message and "\n" not in message, message
    # The command line says the same in one line and exits with 2, before any work.
    code, _, stderr = run(capsys, "render", path, "--rig", "stereo", "--pose", 0, "--out", tmp_path / "out")
    one_line_error(code, stderr, path / file, problem)
    assert not (tmp_path / "out").exists()


def test_save_refuses_half_a_body_or_a_bad_one(tmp_path):
    faces, uv, rest = grid_mesh(4, 4)
    gt = np.stack([rest, rest])
    body_faces, body = _body_sequence(2)
    common = dict(faces=faces, uv=uv, gt=gt, inferred=gt, poses=np.zeros((2, 1)))
    with pytest.raises(InputError, match="both"):
        save_dataset(tmp_path / "a", body_faces=body_faces, **common)
    with pytest.raises(InputError, match="body positions"):
        save_dataset(tmp_path / "b", body_faces=body_faces, body=body[:1], **common)
    with pytest.raises(InputError, match="out of range"):
        save_dataset(tmp_path / "c", body_faces=body_faces + 1, body=body, **common)
    with pytest.raises(InputError, match="NaN"):
        save_dataset(tmp_path / "d", body_faces=body_faces, body=np.full_like(body, np.nan), **common)
    assert list(tmp_path.iterdir()) == []


def test_fingerprint_includes_the_body_only_when_there_is_one(bodied, tiny_dataset):
    from mvtex.util.fingerprint import fingerprint

    plain = load_dataset(tiny_dataset)
    assert fingerprint(plain.gt, plain.inferred, plain.poses, *plain.body_arrays()) == \
        fingerprint(plain.gt, plain.inferred, plain.poses)
    ds = load_dataset(bodied[0])
    with_body = fingerprint(ds.inferred, ds.poses, ds.faces, ds.uv, *ds.body_arrays())
    assert with_body != fingerprint(ds.inferred, ds.poses, ds.faces, ds.uv)
    assert with_body == fingerprint(ds.inferred, ds.poses, ds.faces, ds.uv, bodied[2].astype(np.float32), bodied[1])


def _write_sequences(root, num_poses: int, body_count: int | None = None):
    faces, uv, rest = grid_mesh(6, 5)
    body_faces, body = _body_sequence(num_poses)
    for k in range(num_poses):
        write_obj(root / f"gt_{k:03d}.obj", wave(rest, 0.01, k), uv, faces)
        write_obj(root / f"inf_{k:03d}.obj", wave(rest, 0.003, k), uv, faces)
    for k in range(num_poses if body_count is None else body_count):
        lines = [f"v {x:.9f} {y:.9f} {z:.9f}" for x, y, z in body[k % num_poses]]
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in body_faces]
        (root / f"body_{k:03d}.obj").write_text("\n".join(lines) + "\n")
    return body_faces, body


def test_import_with_a_body_sequence(tmp_path):
    from mvtex.data.importer import import_sequences

    body_faces, body = _write_sequences(tmp_path, 3)
    out = import_sequences(tmp_path / "ds", str(tmp_path / "gt_*.obj"), str(tmp_path / "inf_*.obj"),
                           body_glob=str(tmp_path / "body_*.obj"), progress=False)
    ds = load_dataset(out)
    assert np.array_equal(ds.body.faces, body_faces)
    np.testing.assert_allclose(ds.body.positions, body, atol=1e-7)
    # Without --body the same sequences import as before: no body files.
    plain = import_sequences(tmp_path / "plain", str(tmp_path / "gt_*.obj"), str(tmp_path / "inf_*.obj"),
                             progress=False)
    assert load_dataset(plain).body is None and not (plain / "body.npy").exists()


def test_import_refuses_a_bad_body_sequence(tmp_path):
    from mvtex.data.importer import import_sequences

    _write_sequences(tmp_path, 3, body_count=2)
    gt, inferred = str(tmp_path / "gt_*.obj"), str(tmp_path / "inf_*.obj")
    with pytest.raises(InputError, match="2 body meshes for 3 gt meshes"):
        import_sequences(tmp_path / "ds", gt, inferred, body_glob=str(tmp_path / "body_*.obj"), progress=False)
    # Another connectivity in the third mesh; then a NaN in the second.
    faces, vertices = octahedron(0.1, (0, 0, -0.2))
    lines = [f"v {x:.9f} {y:.9f} {z:.9f}" for x, y, z in vertices]
    flipped = [f"f {a + 1} {c + 1} {b + 1}" for a, b, c in faces]
    same = [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    (tmp_path / "body_002.obj").write_text("\n".join(lines + flipped) + "\n")
    with pytest.raises(InputError, match="body_002.obj: connectivity"):
        import_sequences(tmp_path / "ds", gt, inferred, body_glob=str(tmp_path / "body_*.obj"), progress=False)
    (tmp_path / "body_002.obj").write_text("\n".join(lines + same) + "\n")
    (tmp_path / "body_001.obj").write_text("\n".join(["v nan 0 0"] + lines[1:] + same) + "\n")
    with pytest.raises(InputError, match="body_001.obj: NaN"):
        import_sequences(tmp_path / "ds", gt, inferred, body_glob=str(tmp_path / "body_*.obj"), progress=False)
    with pytest.raises(InputError, match="no body files match"):
        import_sequences(tmp_path / "ds", gt, inferred, body_glob=str(tmp_path / "none_*.obj"), progress=False)
    assert not (tmp_path / "ds").exists()
