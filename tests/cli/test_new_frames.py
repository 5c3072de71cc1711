"""New frames, no ground truth: a trained model's run-time path through the command line.

The frames are the tiny sheet's own inferred meshes and pose vectors written as OBJ files
and imported without --gt; the models are `gp` models of both cameras trained on the full
dataset. What an inference set gives is compared with what the full dataset gives for the
same frames, and with independent numbers (the rig the set was slid with, distances
computed here from the PLY)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import one_line_error, run, write_obj

pytestmark = pytest.mark.gl
torch = pytest.importorskip("torch")


@pytest.fixture(scope="module")
def trained(tmp_path_factory, tiny_dataset, front_rig, gl):
    """The tiny dataset slid from the front rig (all poses, no subdivision), a `gp` model
    per camera, and the dataset's frames as OBJ files (inferred, rest) + poses.txt."""
    from mvtex.data.dataset import load_dataset
    from mvtex.data.texcoords import open_texcoords
    from mvtex.sliding.dataset import slide_dataset
    from mvtex.sliding.options import SlideOptions
    from mvtex.tsnn.train import TrainOptions, train

    root = tmp_path_factory.mktemp("new_frames")
    ds = load_dataset(tiny_dataset)
    slide_dataset(ds, front_rig, root / "ts", poses=list(range(ds.num_poses)), options=SlideOptions(subdiv=0),
                  workers=1, progress=False)
    tc = open_texcoords(root / "ts", ds.num_vertices)
    for cam in ("a", "b"):
        train(ds, tc, root / f"gp_{cam}", camera=cam, options=TrainOptions(components=3), progress=False)
    frames = root / "frames"
    frames.mkdir()
    for k in range(ds.num_poses):
        write_obj(frames / f"inferred_{k:02d}.obj", ds.inferred[k], ds.uv, ds.faces)
    write_obj(frames / "rest.obj", ds.rest, ds.uv, ds.faces)
    np.savetxt(frames / "poses.txt", np.asarray(ds.poses), fmt="%.9g")
    return ds, root


def _import(capsys, root, out, *extra):
    return run(capsys, "import", "--out", out, "--inferred", root / "frames" / "inferred_*.obj", "--pose-vectors",
               root / "frames" / "poses.txt", "--quiet", *extra)


@pytest.mark.slow
def test_run_time_path_on_an_inference_set_equals_the_full_dataset(trained, tmp_path, front_rig, capsys):
    """import (no --gt) -> predict (no --rig) -> triangulate, views, preview, render (no
    --rig): predictions equal the full dataset's for the same frames, the PLY too, the set
    records the cameras the models were trained for, and nothing needs gt."""
    from mvtex.data.dataset import load_dataset
    from mvtex.data.rig import load_rig
    from mvtex.data.texcoords import open_texcoords

    ds, root = trained
    models = ["--model", root / "gp_a", "--model", root / "gp_b"]
    code, out, err = _import(capsys, root, tmp_path / "frames", "--rest", root / "frames" / "rest.obj")
    assert code == 0, err
    assert "inference set (no ground truth), 6 frames" in out
    frames = load_dataset(tmp_path / "frames")
    assert not frames.has_gt and not (tmp_path / "frames" / "gt.npy").exists()

    code, out, err = run(capsys, "predict", tmp_path / "frames", *models, "--out", tmp_path / "pred", "--quiet")
    assert code == 0 and "rig.yaml" in out, err
    assert "warning" not in err
    code, _, err = run(capsys, "predict", ds.path, *models, "--out", tmp_path / "pred_full", "--quiet")
    assert code == 0, err
    new, full = open_texcoords(tmp_path / "pred"), open_texcoords(tmp_path / "pred_full")
    worst = max(np.abs(new.displacement(c, k) - full.displacement(c, k)).max() for c in ("a", "b") for k in range(6))
    assert worst <= 1e-6
    # The set's rig is the rig the models' texcoord set was slid with.
    recorded = load_rig(tmp_path / "pred" / "rig.yaml")
    assert recorded.names == ["a", "b"]
    for cam in front_rig:
        got = recorded[cam.name]
        assert (got.width, got.height) == (cam.width, cam.height)
        for key in ("K", "R", "t"):
            np.testing.assert_allclose(getattr(got, key), getattr(cam, key), rtol=0, atol=1e-12)

    # triangulate without --rig: PLY and COLMAP model; the gt keys are null; the same points
    # as from the full dataset.
    report = json.loads(run(capsys, "triangulate", tmp_path / "frames", "--texcoords", tmp_path / "pred", "--pose", 2,
                            "--out", tmp_path / "rec", "--quiet", "--json")[1])
    assert report["rmse_m"] is None and report["rmse_triangulated_m"] is None
    assert report["strain_energy"]["gt"] is None
    for name in ("reconstruction.ply", "colmap/points3D.bin", "colmap/cameras.bin", "colmap/images.bin"):
        assert (tmp_path / "rec" / name).is_file(), name
    assert not (tmp_path / "rec" / "comparison.png").exists()
    code, _, err = run(capsys, "triangulate", ds.path, "--rig", root / "ts" / "rig.yaml", "--texcoords",
                       tmp_path / "pred_full", "--pose", 2, "--out", tmp_path / "rec_full", "--quiet")
    assert code == 0, err
    import trimesh

    ply = np.asarray(trimesh.load(tmp_path / "rec" / "reconstruction.ply", process=False).vertices, np.float64)
    ply_full = np.asarray(trimesh.load(tmp_path / "rec_full" / "reconstruction.ply", process=False).vertices)
    assert np.abs(ply - ply_full).max() <= 1e-6
    # What it says without gt, against numbers computed here from the PLY and the frames.
    moved = np.linalg.norm(ply - np.asarray(frames.inferred[2], np.float64), axis=1)
    assert report["displacement_m"]["mean"] == pytest.approx(moved.mean(), abs=1e-6)
    assert report["displacement_m"]["max"] == pytest.approx(moved.max(), abs=1e-6)
    assert report["triangulated_share"] == pytest.approx(report["num_triangulated"] / len(ply))
    assert 0 < report["num_triangulated"] and 0 <= report["mean_trust"] <= 1
    code, text, err = run(capsys, "triangulate", tmp_path / "frames", "--texcoords", tmp_path / "pred", "--pose", 2,
                          "--out", tmp_path / "rec2", "--quiet")
    assert code == 0, err
    first = text.splitlines()[0]
    assert first.startswith("pose 2: triangulated") and "mean trust" in first and "moved from the inferred mesh" in first
    assert "no ground truth" in text and "RMSE vs gt" not in text

    # views and preview without --rig; preview skips its gt scores and says so once.
    code, text, err = run(capsys, "views", tmp_path / "frames", "--texcoords", tmp_path / "pred", "--between", "a,b",
                          "--steps", 3, "--poses", "0,2", "--out", tmp_path / "views", "--plot", tmp_path / "p.png",
                          "--quiet")
    assert code == 0, err
    assert open_texcoords(tmp_path / "views").cameras == ["view_000", "view_001", "view_002"]
    assert text.count("no ground truth") == 1 and not (tmp_path / "p.png").exists()
    code, text, err = run(capsys, "preview", tmp_path / "frames", "--texcoords", tmp_path / "pred", "--pose", 2,
                          "--out", tmp_path / "preview", "--quiet")
    assert code == 0, err
    assert (text + err).count("no ground truth") == 1
    preview = json.loads((tmp_path / "preview" / "preview.json").read_text())
    assert preview["ground_truth"] is False and preview["eyes"]["left"]["ssim"] is None
    assert (tmp_path / "preview" / "stereo.png").stat().st_size > 1000
    # render: the inferred pictures alone, with the set's texcoords.
    code, _, err = run(capsys, "render", tmp_path / "frames", "--texcoords", tmp_path / "pred", "--pose", 1, "--out",
                       tmp_path / "render", "--quiet")
    assert code == 0, err
    files = json.loads((tmp_path / "render" / "render.json").read_text())["files"]
    assert "a/inferred.png" in files and not any("gt" in f for f in files)


def test_commands_that_need_gt_refuse_an_inference_set(trained, tmp_path, capsys):
    ds, root = trained
    assert _import(capsys, root, tmp_path / "frames")[0] == 0
    frames = tmp_path / "frames"
    rig = root / "ts" / "rig.yaml"
    code, _, err = run(capsys, "slide", frames, "--rig", rig, "--out", tmp_path / "ts")
    one_line_error(code, err, frames, "no ground truth", "slide needs")
    code, _, err = run(capsys, "eval", frames, "--rig", rig, "--texcoords", root / "ts", "--heatmaps",
                       tmp_path / "heat")
    one_line_error(code, err, frames, "no ground truth", "eval needs")
    code, _, err = run(capsys, "bench", frames, "--rig", rig, "--workers", 1)
    one_line_error(code, err, frames, "no ground truth", "bench needs")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames"]


def test_a_model_refuses_frames_it_cannot_serve(trained, tmp_path, capsys):
    """One line naming the model's config.json and the set: another vertex count, other
    uv, pose vectors of another dimension; nothing written."""
    from mvtex.data.dataset import load_dataset, save_dataset

    ds, root = trained
    frames = load_dataset(ds.path)
    arrays = dict(faces=frames.faces, inferred=np.asarray(frames.inferred))
    save_dataset(tmp_path / "uv", uv=frames.uv * 0.5, gt=None, poses=np.asarray(frames.poses), **arrays)
    save_dataset(tmp_path / "pose3", uv=frames.uv, gt=None, poses=np.c_[frames.poses, np.zeros(6)], **arrays)
    save_dataset(tmp_path / "small", faces=frames.faces[:10], uv=frames.uv[:40], gt=None,
                 inferred=np.asarray(frames.inferred)[:, :40], poses=np.asarray(frames.poses))
    for name, needles in (("uv", ("another mesh", "other faces or uv")), ("pose3", ("2-dimensional", "3-dimensional")),
                          ("small", ("vertices", "has 40"))):
        code, _, err = run(capsys, "predict", tmp_path / name, "--model", root / "gp_a", "--out", tmp_path / "p")
        one_line_error(code, err, root / "gp_a" / "config.json", tmp_path / name, *needles)
        assert not (tmp_path / "p").exists()


@pytest.mark.parametrize("damage,needle", [
    ("nan", "NaN"), ("vertices", "vertices, expected"), ("pose_dim", "poses"), ("body", "body meshes for"),
    ("rest", "vertices, expected"),
])
def test_bad_new_frames_are_refused_with_one_line(trained, tmp_path, capsys, damage, needle):
    """An inference set with NaN, a wrong vertex count, pose vectors of another dimension,
    a body of another frame count, a rest mesh of another mesh: exit 2, one line naming the
    file, nothing written."""
    ds, root = trained
    src = root / "frames"
    frames = tmp_path / "in"
    frames.mkdir()
    for k in range(ds.num_poses):
        (frames / f"inferred_{k:02d}.obj").write_text((src / f"inferred_{k:02d}.obj").read_text())
    poses = (src / "poses.txt").read_text()
    extra: list = []
    named = frames / "inferred_03.obj"
    if damage == "nan":
        text = named.read_text().splitlines()
        text[5] = "v nan 0 0"
        named.write_text("\n".join(text) + "\n")
    elif damage == "vertices":
        write_obj(named, ds.inferred[3][:40], ds.uv[:40], ds.faces[:10])
    elif damage == "pose_dim":
        rows = poses.splitlines()
        rows[4] += " 0.5"  # one row of 3 numbers among rows of 2
        poses = "\n".join(rows) + "\n"
        named = frames / "poses.txt"
    elif damage == "body":
        for k in range(ds.num_poses - 1):
            write_obj(frames / f"body_{k:02d}.obj", ds.inferred[k] + [0, 0, -0.2], ds.uv, ds.faces)
        extra = ["--body", frames / "body_*.obj"]
        named = frames / "body_*.obj"
    elif damage == "rest":
        write_obj(frames / "rest.obj", ds.rest[:40], ds.uv[:40], ds.faces[:10])
        extra = ["--rest", frames / "rest.obj"]
        named = frames / "rest.obj"
    (frames / "poses.txt").write_text(poses)
    code, _, err = run(capsys, "import", "--out", tmp_path / "set", "--inferred", frames / "inferred_*.obj",
                       "--pose-vectors", frames / "poses.txt", "--quiet", *extra)
    one_line_error(code, err, named, needle)
    assert not (tmp_path / "set").exists()


def test_models_record_their_cameras_and_older_models_say_why_the_set_has_no_rig(trained, tmp_path, capsys):
    """config.json records the training camera whole (ModelConfig reads what it writes); a
    model without that record predicts, says once why the set records no rig, and the
    command after it asks for --rig."""
    from mvtex.tsnn.config import ModelConfig

    ds, root = trained
    config = ModelConfig.read(root / "gp_a")
    assert config.rig.names == ["a"] and config.camera == "a"
    assert ModelConfig.from_json(config.to_json(), "x").to_json() == json.loads((root / "gp_a" / "config.json")
                                                                                .read_text())
    import shutil

    old = tmp_path / "old_a"
    shutil.copytree(root / "gp_a", old)
    meta = json.loads((old / "config.json").read_text())
    del meta["rig"]
    (old / "config.json").write_text(json.dumps(meta))
    code, out, err = run(capsys, "predict", ds.path, "--model", old, "--model", root / "gp_b", "--out",
                         tmp_path / "pred", "--quiet")
    assert code == 0, err
    assert err.count("warning") == 1 and str(old / "config.json") in err and "--rig" in err
    assert not (tmp_path / "pred" / "rig.yaml").exists() and "no rig recorded" in out
    code, _, err = run(capsys, "triangulate", ds.path, "--texcoords", tmp_path / "pred", "--pose", 1, "--out",
                       tmp_path / "rec")
    one_line_error(code, err, "--rig", "records no rig")
    # A malformed record names the file and the key.
    meta["rig"] = {"a": {"width": 160, "height": 120, "K": [[1, 0]], "R": np.eye(3).tolist(), "t": [0, 0, 0]}}
    (old / "config.json").write_text(json.dumps(meta))
    code, _, err = run(capsys, "predict", ds.path, "--model", old, "--out", tmp_path / "p2")
    one_line_error(code, err, old / "config.json", "rig.a")
