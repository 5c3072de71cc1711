"""Novel views: interpolated cameras against SciPy and closed forms, blend identities, the
reconstruct method against blend and direct texture sliding, and the CLI's bad input."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import run
from scipy.spatial.transform import Rotation, Slerp

from mvtex.data.rig import builtin_rig_file, load_rig, save_rig
from mvtex.views.cameras import between_weights, grid_weights, interpolate_camera
from mvtex.views.synthesizer import blend_displacement


@pytest.fixture(scope="module")
def garment(tmp_path_factory, gl):
    """The built-in garment (12 poses) slid from the stereo rig on two test poses."""
    from mvtex.data.dataset import load_dataset
    from mvtex.sliding.dataset import slide_dataset
    from mvtex.sliding.options import SlideOptions
    from mvtex.synth.generate import SynthOptions, write_synth

    root = tmp_path_factory.mktemp("garment")
    write_synth(root / "shirt", SynthOptions(num_poses=12, seed=0))
    ds = load_dataset(root / "shirt")
    poses = ds.split["test"][:1] + ds.split["val"][:1]
    slide_dataset(ds, load_rig(builtin_rig_file("stereo")), root / "ts", poses=poses, options=SlideOptions(subdiv=1),
                  workers=1, progress=False)
    return ds, root / "ts", poses


def _slerp_closed_form(q0: np.ndarray, q1: np.ndarray, t: float) -> np.ndarray:
    """Shoemake's slerp on unit quaternions, shortest arc."""
    if np.dot(q0, q1) < 0:
        q1 = -q1
    omega = np.arccos(np.clip(np.dot(q0, q1), -1, 1))
    return (np.sin((1 - t) * omega) * q0 + np.sin(t * omega) * q1) / np.sin(omega)


def test_midpoint_camera_is_slerp_and_mean(tmp_path, sheet_set, capsys):
    dataset, rig_path, ts = sheet_set
    code, _, err = run(capsys, "views", dataset, "--rig", rig_path, "--texcoords", ts, "--out", tmp_path / "v",
                       "--between", "a,b", "--steps", 3, "--method", "blend", "--quiet")
    assert code == 0, err
    rig = load_rig(rig_path)
    mid = load_rig(tmp_path / "v" / "rig.yaml")["view_001"]
    a, b = rig["a"], rig["b"]
    expected = Slerp([0, 1], Rotation.from_matrix([a.R, b.R]))([0.5]).as_matrix()[0]
    assert np.abs(mid.R - expected).max() < 1e-9
    q = _slerp_closed_form(Rotation.from_matrix(a.R).as_quat(), Rotation.from_matrix(b.R).as_quat(), 0.5)
    assert np.abs(mid.R - Rotation.from_quat(q).as_matrix()).max() < 1e-9
    assert np.abs(mid.center - (a.center + b.center) / 2).max() < 1e-9
    assert np.abs(mid.K - (a.K + b.K) / 2).max() < 1e-9


def test_four_camera_average_matches_scipy_mean():
    rig = load_rig(builtin_rig_file("square4"))
    w = {"tl": 0.1, "tr": 0.2, "bl": 0.3, "br": 0.4}
    cam = interpolate_camera(rig, w, "v")
    expected = Rotation.from_matrix([rig[n].R for n in w]).mean(weights=list(w.values())).as_matrix()
    assert np.abs(cam.R - expected).max() < 1e-9
    assert np.abs(cam.center - sum(x * rig[n].center for n, x in w.items())).max() < 1e-9


def test_grid_and_between_weights():
    grid = grid_weights("A", "B", "C", "D", 3)
    assert grid[0] == {"A": 1.0, "B": 0.0, "C": 0.0, "D": 0.0}
    assert grid[2]["B"] == 1.0 and grid[6]["C"] == 1.0 and grid[8]["D"] == 1.0  # row-major from A
    assert grid[4] == {"A": 0.25, "B": 0.25, "C": 0.25, "D": 0.25}
    assert [w["B"] for w in between_weights("A", "B", 5)] == [0.0, 0.25, 0.5, 0.75, 1.0]


@pytest.mark.parametrize("method", ["blend", "reconstruct"])
def test_weight_one_reproduces_the_camera(tmp_path, sheet_set, capsys, method, monkeypatch):
    import mvtex.views.novel
    from mvtex.data.texcoords import open_texcoords

    monkeypatch.setattr(mvtex.views.novel, "_WRITE_BLOCK", 2)  # 3 poses: a full block and a partial one
    dataset, rig_path, ts = sheet_set
    code, _, err = run(capsys, "views", dataset, "--rig", rig_path, "--texcoords", ts, "--out", tmp_path / "v",
                       "--weights", "a=0,b=1", "--name", "same_as_b", "--method", method, "--quiet")
    assert code == 0, err
    cam = load_rig(tmp_path / "v" / "rig.yaml")["same_as_b"]
    b = load_rig(rig_path)["b"]
    assert np.array_equal(cam.K, b.K) and np.array_equal(cam.R, b.R) and np.array_equal(cam.t, b.t)
    src, out = open_texcoords(ts), open_texcoords(tmp_path / "v")
    for k in src.poses:
        assert np.array_equal(out.displacement("same_as_b", k).view(np.uint32), src.displacement("b", k).view(np.uint32))
        assert np.array_equal(out.assigned("same_as_b", k), src.assigned("b", k))


@pytest.mark.slow
@pytest.mark.parametrize("method", ["blend", "reconstruct"])
def test_views_on_worker_processes_equal_one_process(tmp_path, sheet_set, capsys, method):
    dataset, rig_path, ts = sheet_set
    trees = []
    for workers in ("1", "2"):
        out = tmp_path / f"v{workers}"
        code, _, err = run(capsys, "views", dataset, "--rig", rig_path, "--texcoords", ts, "--out", out,
                           "--between", "a,b", "--steps", 3, "--method", method, "--workers", workers, "--quiet")
        assert code == 0, err
        trees.append({p.relative_to(out): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()})
    assert len(trees[0]) > 4 and trees[0] == trees[1]


def test_blend_of_identical_sets_is_identity():
    rng = np.random.default_rng(1)
    d = rng.normal(0, 0.01, (500, 2)).astype(np.float32)
    a = rng.random(500) > 0.2
    out, assigned = blend_displacement({"p": d, "q": d.copy()}, {"p": a, "q": a.copy()}, {"p": 0.3, "q": 0.7})
    assert np.array_equal(out, d)
    assert np.array_equal(assigned, a)
    other = rng.normal(0, 0.01, (500, 2)).astype(np.float32)
    mixed, _ = blend_displacement({"p": d, "q": other}, {"p": a, "q": a}, {"p": 0.25, "q": 0.75})
    assert np.allclose(mixed, 0.25 * d.astype(np.float64) + 0.75 * other, atol=1e-8)


@pytest.mark.slow
def test_reconstruct_beats_blend_at_the_stereo_midpoint(tmp_path, garment):
    """On the built-in garment, reconstruct is closer to TS computed directly at the view."""
    from mvtex.views.measure import measure_views

    ds, ts, poses = garment
    from mvtex.data.texcoords import open_texcoords

    rig = load_rig(builtin_rig_file("stereo"))
    measured = measure_views(ds, rig, open_texcoords(ts, ds.num_vertices), [{"left": 0.5, "right": 0.5}], ["mid"],
                             progress=False)
    same = {k: v[0] for k, v in measured["sqrt_mse_same_chart"].items()}
    assert same["direct TS"] < same["reconstruct"] < same["blend"] < same["baseline"], same


@pytest.mark.parametrize("args, needle", [
    (["--weights", "a=0.5,b=0.6"], "sum to 1"),
    (["--weights", "a=1.5,b=-0.5"], ">= 0"),
    (["--weights", "a=0.5,zz=0.5"], "zz"),
    (["--weights", "a=half"], "NAME=NUMBER"),
    (["--between", "a,zz", "--steps", "3"], "zz"),
    (["--between", "a,b"], "--steps"),
    (["--grid", "a,b", "--steps", "3"], "4 camera names"),
    (["--weights", "a=0.5,b=0.5", "--name", "../x"], "not allowed"),
])
def test_bad_weights_exit_2_with_one_line(tmp_path, sheet_set, capsys, args, needle):
    dataset, rig_path, ts = sheet_set
    code, out, err = run(capsys, "views", dataset, "--rig", rig_path, "--texcoords", ts, "--out", tmp_path / "v",
                         *args, "--quiet")
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and needle in err, err
    assert out == ""
    assert not (tmp_path / "v").exists() and not (tmp_path / "v.partial").exists()


def test_texcoords_from_another_rig_exit_2(tmp_path, sheet_set, capsys):
    dataset, rig_path, ts = sheet_set
    code, _, err = run(capsys, "views", dataset, "--rig", "stereo", "--texcoords", ts, "--out", tmp_path / "v",
                       "--weights", "left=0.5,right=0.5", "--quiet")
    assert code == 2 and len(err.strip().splitlines()) == 1 and "another rig" in err, err
    # Same names, other cameras: also refused.
    rig = load_rig(rig_path)
    from dataclasses import replace

    moved = type(rig)(tuple(replace(c, t=c.t + 0.1) for c in rig))
    save_rig(moved, tmp_path / "moved.yaml")
    code, _, err = run(capsys, "views", dataset, "--rig", tmp_path / "moved.yaml", "--texcoords", ts, "--out",
                       tmp_path / "v", "--weights", "a=0.5,b=0.5", "--quiet")
    assert code == 2 and len(err.strip().splitlines()) == 1 and "other parameters" in err, err
    assert not (tmp_path / "v").exists()


@pytest.mark.slow
def test_views_never_replace_a_folder_they_did_not_write(tmp_path, sheet_set, capsys):
    dataset, rig_path, ts = sheet_set
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "keep.txt").write_text("x")
    argv = ["views", dataset, "--rig", rig_path, "--texcoords", ts, "--weights", "a=0.5,b=0.5", "--quiet"]
    code, _, err = run(capsys, *argv, "--out", mine)
    assert code == 2 and len(err.strip().splitlines()) == 1 and "--overwrite" in err, err
    assert sorted(p.name for p in mine.iterdir()) == ["keep.txt"]
    # Its own earlier output is replaced on a rerun.
    assert run(capsys, *argv, "--out", tmp_path / "v")[0] == 0
    assert run(capsys, *argv, "--out", tmp_path / "v")[0] == 0
    assert (tmp_path / "v" / "texcoords.json").is_file()


@pytest.mark.slow
def test_interrupted_views_continue_where_they_stopped(tmp_path, sheet_set, capsys, monkeypatch):
    """A views run stopped after its first block leaves OUT.partial; the rerun computes only
    the missing blocks and writes the files an uninterrupted run writes, byte for byte.
    Other settings start over (said on stderr); a foreign OUT.partial is refused."""
    import mvtex.views.novel

    monkeypatch.setattr(mvtex.views.novel, "_WRITE_BLOCK", 2)  # 3 poses: blocks of 2 and 1
    dataset, rig_path, ts = sheet_set
    argv = ["views", dataset, "--rig", rig_path, "--texcoords", ts, "--between", "a,b", "--steps", 3,
            "--method", "reconstruct", "--quiet"]
    assert run(capsys, *argv, "--out", tmp_path / "whole")[0] == 0
    whole = {p.relative_to(tmp_path / "whole"): p.read_bytes() for p in sorted((tmp_path / "whole").rglob("*"))
             if p.is_file()}

    real = mvtex.views.novel._views_of_poses
    blocks = []

    def stop_after_one(synth, cameras, weights, poses, tick=None):
        if blocks:
            raise KeyboardInterrupt
        blocks.append(list(poses))
        return real(synth, cameras, weights, poses, tick=tick)

    monkeypatch.setattr(mvtex.views.novel, "_views_of_poses", stop_after_one)
    out = tmp_path / "v"
    assert run(capsys, *argv, "--out", out)[0] == 130  # as Ctrl-C
    assert not out.exists() and (tmp_path / "v.partial" / "view_000" / "done.npy").is_file()

    def count(synth, cameras, weights, poses, tick=None):
        blocks.append(list(poses))
        return real(synth, cameras, weights, poses, tick=tick)

    # As if killed while saving the done mask: its hidden temporary copy is left behind.
    from mvtex.util.output import _temporary

    (_temporary(tmp_path / "v.partial" / "view_000" / "done.npy", "tmp") / "done.npy").write_bytes(b"")
    monkeypatch.setattr(mvtex.views.novel, "_views_of_poses", count)
    assert run(capsys, *argv, "--out", out)[0] == 0
    assert blocks == [[0, 2], [4]]  # the second run computed only the block the first did not finish
    assert not (tmp_path / "v.partial").exists() and not list(out.rglob("done.npy"))
    assert {p.relative_to(out): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()
            and p.name != ".mvtex-output.json"} == {k: v for k, v in whole.items() if k.name != ".mvtex-output.json"}

    # Stopped again, then rerun with other views: that partial is not reused.
    monkeypatch.setattr(mvtex.views.novel, "_views_of_poses", stop_after_one)
    assert run(capsys, *argv, "--out", tmp_path / "w")[0] == 130
    monkeypatch.setattr(mvtex.views.novel, "_views_of_poses", real)
    code, _, err = run(capsys, "views", dataset, "--rig", rig_path, "--texcoords", ts, "--weights", "a=0.25,b=0.75",
                       "--name", "q", "--method", "reconstruct", "--quiet", "--out", tmp_path / "w")
    assert code == 0 and "starting over" in err
    # A folder named like a partial that views did not write: exit 2, untouched.
    (tmp_path / "x.partial").mkdir()
    (tmp_path / "x.partial" / "keep.txt").write_text("x")
    code, _, err = run(capsys, *argv, "--out", tmp_path / "x")
    assert code == 2 and len(err.strip().splitlines()) == 1 and "x.partial" in err
    assert [p.name for p in (tmp_path / "x.partial").iterdir()] == ["keep.txt"]
