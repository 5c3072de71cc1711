"""Dataset format, pose specs, subdivision and the OBJ/PLY importer."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import grid_mesh, wave, write_obj

from mvtex.data.dataset import default_split, load_dataset, parse_pose_spec, save_dataset
from mvtex.data.mesh import edges, subdivide
from mvtex.util.errors import InputError


def test_round_trip_is_memory_mapped(tiny_dataset):
    ds = load_dataset(tiny_dataset)
    assert isinstance(ds.gt, np.memmap) and ds.gt.dtype == np.float32
    assert ds.gt.shape == ds.inferred.shape == (6, len(ds.uv), 3)
    meta = json.loads((tiny_dataset / "dataset.json").read_text())
    assert meta["format"] == "mvtex-dataset" and meta["num_vertices"] == len(ds.uv) and meta["pose_dim"] == 2
    assert sorted(ds.split["train"] + ds.split["val"] + ds.split["test"]) == list(range(6))


def test_default_split_is_seeded_80_10_10():
    a, b = default_split(100, seed=3), default_split(100, seed=3)
    assert a == b and [len(a[k]) for k in ("train", "val", "test")] == [80, 10, 10]
    assert len(set(a["train"]) | set(a["val"]) | set(a["test"])) == 100


@pytest.mark.parametrize("num_poses", [3, 4, 7, 10, 23])
def test_default_split_of_small_datasets_has_train_and_test(num_poses):
    split = default_split(num_poses)
    assert split["train"] and split["test"] and split["val"]
    assert sorted(split["train"] + split["val"] + split["test"]) == list(range(num_poses))


def test_default_split_of_fewer_than_three_poses_is_all_train():
    assert default_split(2) == {"train": [0, 1], "val": [], "test": []}


@pytest.mark.parametrize("spec,expected", [("all", list(range(10))), ("2:5", [2, 3, 4]), ("3,5,7", [3, 5, 7]),
                                           ("::4", [0, 4, 8]), ("-2:", [8, 9])])
def test_pose_specs(spec, expected):
    assert parse_pose_spec(spec, 10) == expected


@pytest.mark.parametrize("spec", ["12", "a:b", "1,x", "5:5"])
def test_bad_pose_specs(spec):
    with pytest.raises(InputError):
        parse_pose_spec(spec, 10)


def test_subdivision_parent_map_and_midpoints():
    faces, uv, rest = grid_mesh(5, 4)
    n = len(uv)
    for levels in (1, 2):
        sub = subdivide(faces, n, levels)
        assert len(sub.faces) == len(faces) * 4**levels
        assert np.array_equal(sub.parent[:n], np.stack([np.arange(n)] * 2, 1))
        assert np.all(sub.parent[n:].max(axis=1) < np.arange(n, sub.num_vertices))  # parents precede children
        # Positions of a flat grid: every new vertex is the exact midpoint (closed form).
        pos = sub.apply(rest)
        for j in range(n, sub.num_vertices):
            a, b = sub.parent[j]
            assert np.allclose(pos[j], 0.5 * (pos[a] + pos[b]))
        # Euler characteristic is preserved and every edge is shared by at most two faces.
        V, E, F = sub.num_vertices, len(edges(sub.faces)), len(sub.faces)
        assert V - E + F == n - len(edges(faces)) + len(faces)


def test_import_obj_sequences(tmp_path):
    faces, uv, rest = grid_mesh(6, 5)
    for k in range(3):
        write_obj(tmp_path / f"gt_{k:03d}.obj", wave(rest, 0.01, k), uv, faces)
        write_obj(tmp_path / f"inf_{k:03d}.obj", wave(rest, 0.003, k), uv, faces)
    from mvtex.data.importer import import_sequences

    out = import_sequences(tmp_path / "ds", str(tmp_path / "gt_*.obj"), str(tmp_path / "inf_*.obj"))
    ds = load_dataset(out)
    assert np.array_equal(ds.faces, faces)
    assert np.allclose(ds.uv, uv, atol=1e-6)
    assert np.allclose(ds.gt[2], wave(rest, 0.01, 2), atol=1e-6)


def test_import_refuses_different_connectivity(tmp_path):
    faces, uv, rest = grid_mesh(6, 5)
    write_obj(tmp_path / "gt_0.obj", rest, uv, faces)
    write_obj(tmp_path / "gt_1.obj", rest, uv, faces[:, [0, 2, 1]])
    write_obj(tmp_path / "inf_0.obj", rest, uv, faces)
    write_obj(tmp_path / "inf_1.obj", rest, uv, faces)
    from mvtex.data.importer import import_sequences

    with pytest.raises(InputError, match="gt_1.obj: connectivity"):
        import_sequences(tmp_path / "ds", str(tmp_path / "gt_*.obj"), str(tmp_path / "inf_*.obj"))
    assert not (tmp_path / "ds").exists()


def _corrupt(tiny_dataset, tmp_path, name, mutate):
    import shutil

    path = tmp_path / "bad"
    shutil.copytree(tiny_dataset, path)
    mutate(path)
    return path


def test_validation_names_the_file(tiny_dataset, tmp_path):
    def nan(path):
        a = np.load(path / "gt.npy")
        a[3, 5, 1] = np.nan
        np.save(path / "gt.npy", a)

    with pytest.raises(InputError, match=r"gt.npy: NaN.*pose 3"):
        load_dataset(_corrupt(tiny_dataset, tmp_path / "a", "gt", nan))

    def count(path):
        np.save(path / "inferred.npy", np.load(path / "inferred.npy")[:, :-1])

    with pytest.raises(InputError, match="inferred.npy: vertex count"):
        load_dataset(_corrupt(tiny_dataset, tmp_path / "b", "inf", count))

    def faces(path):
        z = dict(np.load(path / "mesh.npz"))
        z["faces"][0, 0] = 10**6
        np.savez(path / "mesh.npz", **z)

    with pytest.raises(InputError, match="mesh.npz: face index out of range"):
        load_dataset(_corrupt(tiny_dataset, tmp_path / "c", "faces", faces))

    def meta(path):
        (path / "dataset.json").write_text("{not json")

    with pytest.raises(InputError, match="dataset.json: malformed JSON"):
        load_dataset(_corrupt(tiny_dataset, tmp_path / "d", "meta", meta))


def test_save_is_atomic_on_bad_input(tmp_path):
    faces, uv, rest = grid_mesh(4, 4)
    gt = np.stack([rest, rest])
    with pytest.raises(InputError):
        save_dataset(tmp_path / "ds", faces=faces, uv=uv, gt=gt, inferred=gt[:, :-1], poses=np.zeros((2, 1)))
    assert not (tmp_path / "ds").exists()
    assert list(tmp_path.iterdir()) == []


def _mapped_rss_kb(path) -> int:
    """Resident kB of this process's mappings of `path` (/proc/self/smaps)."""
    total, inside = 0, False
    for line in open("/proc/self/smaps"):
        fields = line.split()
        if "-" in fields[0] and len(fields) >= 5:  # a mapping's header line
            inside = len(fields) >= 6 and fields[-1] == str(path)
        elif inside and fields[0] == "Rss:":
            total += int(fields[1])
    return total


def test_read_rows_reads_maps_through_the_file(tmp_path):
    from mvtex.util.files import load_npy, read_rows
    from mvtex.util.fingerprint import fingerprint

    values = np.random.default_rng(0).normal(size=(300, 50, 3)).astype(np.float32)
    np.save(tmp_path / "a.npy", values)
    np.save(tmp_path / "f.npy", np.asfortranarray(values))
    mapped, fortran = load_npy(tmp_path / "a.npy"), load_npy(tmp_path / "f.npy")
    for start, stop in ((0, 300), (2, 5), (295, 400), (6, 3), (-4, -1)):
        for source in (mapped, values, mapped[10:], fortran):
            rows = read_rows(source, start, stop)
            np.testing.assert_array_equal(rows, np.asarray(source)[start:stop])
            assert type(rows) is np.ndarray and not np.shares_memory(rows, source)
    assert fingerprint(mapped, fortran) == fingerprint(values, np.asfortranarray(values))
    if not __import__("os").path.exists("/proc/self/smaps"):
        return
    # Nothing of a file read by read_rows becomes resident through its map; a plain read
    # through the map does.
    path = (tmp_path / "b.npy").resolve()
    np.save(path, values)
    mapped = load_npy(path)
    np.testing.assert_array_equal(read_rows(mapped, 0, len(mapped)), values)
    assert fingerprint(mapped) == fingerprint(values)
    assert _mapped_rss_kb(path) == 0
    np.testing.assert_array_equal(np.array(mapped), values)
    assert _mapped_rss_kb(path) >= values.nbytes // 1024 // 2


def test_write_npy_rows_writes_through_the_file(tmp_path):
    from numpy.lib.format import open_memmap

    from mvtex.util.files import write_npy_rows

    rng = np.random.default_rng(1)
    for dtype, shape in ((np.float32, (40, 7, 2)), (np.bool_, (40, 7))):
        path = tmp_path / f"{np.dtype(dtype).name}.npy"
        open_memmap(path, mode="w+", dtype=dtype, shape=shape).flush()
        expected = np.zeros(shape, dtype)
        # Runs of consecutive rows, gaps, a single row, the last row, rows out of order.
        for rows in ([0, 1, 2], [5, 9, 10, 11, 20], [39], [30, 29]):
            values = rng.normal(size=(len(rows), *shape[1:])).astype(dtype) if dtype is np.float32 \
                else rng.random((len(rows), *shape[1:])) < 0.5
            write_npy_rows(path, rows, values)
            expected[rows] = values
        np.testing.assert_array_equal(np.load(path), expected)
        with pytest.raises(ValueError, match="outside"):
            write_npy_rows(path, [40], expected[:1])
        with pytest.raises(ValueError, match="do not fit"):
            write_npy_rows(path, [0], expected[:1].astype(np.float64))
        np.testing.assert_array_equal(np.load(path), expected)


def test_texcoord_rows_are_read_through_the_file(tmp_path):
    """Opening a texcoord set (which checks every displacement) and reading all its rows
    leaves nothing of its files resident through the maps, and returns copies."""
    from mvtex.data.texcoords import open_texcoords, save_texcoords

    rng = np.random.default_rng(2)
    n, k = 500, 40
    uv = rng.random((n, 2)).astype(np.float32)
    d = {"a": (rng.normal(size=(k, n, 2)) * 1e-3).astype(np.float32)}
    asg = {"a": rng.random((k, n)) < 0.5}
    faces = np.array([[0, 1, 2]])
    save_texcoords(tmp_path / "tc", faces=faces, uv=uv, parent=np.stack([np.arange(n)] * 2, 1), source="synthetic",
                   subdiv=0, poses=list(range(k)), displacement=d, assigned=asg)
    tc = open_texcoords(tmp_path / "tc")
    for pose in range(k):
        row = tc.displacement("a", pose)
        np.testing.assert_array_equal(row, d["a"][pose])
        np.testing.assert_array_equal(tc.assigned("a", pose), asg["a"][pose])
        assert row.base is None or not isinstance(row.base, np.memmap)
    if not __import__("os").path.exists("/proc/self/smaps"):
        return
    for name in ("displacement.npy", "assigned.npy"):
        assert _mapped_rss_kb((tmp_path / "tc" / "a" / name).resolve()) == 0


def test_texcoord_uncertainty_is_optional_and_checked(tmp_path):
    """`uncertainty.npy` is optional per camera: read back row by row where written, None
    where not; a file of the wrong shape or with a negative or NaN value is refused,
    naming the file."""
    from mvtex.data.texcoords import open_texcoords, save_texcoords
    from mvtex.util.errors import InputError

    rng = np.random.default_rng(3)
    n, k = 30, 4
    uv = rng.random((n, 2)).astype(np.float32)
    d = {c: (rng.normal(size=(k, n, 2)) * 1e-3).astype(np.float32) for c in ("a", "b")}
    asg = {c: np.ones((k, n), bool) for c in d}
    std = rng.random((k, n)).astype(np.float32) * 1e-3
    save_texcoords(tmp_path / "tc", faces=np.array([[0, 1, 2]]), uv=uv, parent=np.stack([np.arange(n)] * 2, 1),
                   source="tsnn", subdiv=0, poses=[7, 3, 5, 1], displacement=d, assigned=asg,
                   uncertainty={"a": std})
    tc = open_texcoords(tmp_path / "tc", n)
    np.testing.assert_array_equal(tc.uncertainty("a", 5), std[2])
    assert tc.has_uncertainty("a") and not tc.has_uncertainty("b") and tc.uncertainty("b", 5) is None
    for bad in (std[:, :-1], np.where(np.arange(n) == 3, -1.0, std).astype(np.float32),
                np.where(np.arange(n) == 3, np.nan, std).astype(np.float32)):
        np.save(tmp_path / "tc" / "a" / "uncertainty.npy", bad)
        with pytest.raises(InputError, match="uncertainty.npy"):
            open_texcoords(tmp_path / "tc", n).uncertainty("a", 5)
