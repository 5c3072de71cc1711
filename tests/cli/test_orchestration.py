"""The orchestration: every command through `main(argv)` with `--json` parsed and checked,
worker processes against one process, the reference shape, `bench`'s agreement claim,
and the sliding options that only the orchestration exercises (`cross_chart`,
`max_displacement`)."""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np
import pytest
from helpers import fail_slide_pose, run, run_json

from mvtex.cli import build_parser, main
from mvtex.data.camera import look_at


def test_every_option_has_a_help_line():
    parser = build_parser()
    subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    missing = [a.dest for a in parser._actions if not a.help]
    for name, sub in subparsers.choices.items():
        missing += [f"{name} {a.option_strings or a.dest}" for a in sub._actions if not (a.help and a.help.strip())]
    assert not missing, missing
    # Every subcommand has a help line in the command list too.
    assert all(choice.help for choice in subparsers._choices_actions)


def test_version(capsys):
    from mvtex import __version__

    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"mvtex {__version__}"


def test_synth_json(tmp_path, capsys):
    from mvtex.data.dataset import load_dataset

    stats = run_json(capsys, "synth", "--out", tmp_path / "shirt", "--num-poses", 10)
    ds = load_dataset(tmp_path / "shirt")
    assert stats["num_vertices"] == ds.num_vertices and stats["num_faces"] == len(ds.faces)
    assert json.loads((tmp_path / "shirt" / "dataset.json").read_text())["stats"] == stats
    assert ds.split["train"] and ds.split["test"] and ds.split["val"]


@pytest.fixture(scope="module")
def norest(tmp_path_factory, tiny_dataset):
    """The tiny dataset without a rest shape: the reference shape is then gt of pose 0."""
    from mvtex.data.dataset import load_dataset, save_dataset

    ds = load_dataset(tiny_dataset)
    path = tmp_path_factory.mktemp("norest") / "sheet"
    save_dataset(path, faces=ds.faces, uv=ds.uv, gt=np.asarray(ds.gt), inferred=np.asarray(ds.inferred),
                 poses=np.asarray(ds.poses), name="sheet-norest", rest=None, split=ds.split)
    return path


@pytest.mark.slow
@pytest.mark.gl
def test_slide_is_independent_of_workers_and_pose_subset(gl, norest, rig_file, tmp_path, capsys):
    """Without a rest shape the topology, seam groups, fill Laplacian and edge breaking are
    measured on gt of pose 0 in every process: pose 3 gets bit-identical d and assigned
    flags with 1 or 2 worker processes and in two different pose subsets."""
    from mvtex.data.texcoords import open_texcoords

    runs = {"one": ("1,3,4", 1), "two": ("1,3,4", 2), "other": ("3,5", 1)}
    sets = {}
    for name, (poses, workers) in runs.items():
        code, _, err = run(capsys, "slide", norest, "--rig", rig_file, "--out", tmp_path / name, "--poses", poses,
                           "--workers", workers, "--quiet")
        assert code == 0, err
        sets[name] = open_texcoords(tmp_path / name)
    meta = sets["one"].meta
    assert meta["reference"]["shape"] == "gt[0]"
    assert {s.meta["reference"]["fingerprint"] for s in sets.values()} == {meta["reference"]["fingerprint"]}
    for cam in sets["one"].cameras:
        d, a = sets["one"].displacement(cam, 3), sets["one"].assigned(cam, 3)
        assert a.mean() > 0.3
        for name in ("two", "other"):
            assert np.array_equal(sets[name].displacement(cam, 3).view(np.uint32), d.view(np.uint32))
            assert np.array_equal(sets[name].assigned(cam, 3), a)
        for pose in (1, 4):
            assert np.array_equal(sets["two"].displacement(cam, pose), sets["one"].displacement(cam, pose))


@pytest.mark.gl
def test_resume_starts_over_when_the_reference_shape_changed(gl, norest, rig_file, tmp_path, monkeypatch, capsys):
    import mvtex.sliding.dataset as jobs
    from mvtex.data.dataset import load_dataset
    from mvtex.sliding.options import SlideOptions

    monkeypatch.setattr(jobs, "_CHUNK", 1)
    original = jobs.slide_pose
    fail_slide_pose(monkeypatch, 2, KeyboardInterrupt())
    ds = load_dataset(norest)
    with pytest.raises(KeyboardInterrupt):
        jobs.slide_dataset(ds, rig_file, tmp_path / "tc", poses=[1, 2], options=SlideOptions(subdiv=0), progress=False)
    monkeypatch.setattr(jobs, "slide_pose", original)
    # The same dataset with a rest shape: another reference shape, so the partial result is stale.
    moved = dataclasses.replace(ds, rest=np.asarray(ds.gt[5]))
    jobs.slide_dataset(moved, rig_file, tmp_path / "tc", poses=[1, 2], options=SlideOptions(subdiv=0), progress=False)
    assert "starting over" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.gl
def test_eval_json_matches_the_library(gl, tiny_dataset, rig_file, slid_sheet, capsys):
    from mvtex.evaluation.evaluate import evaluate

    result = run_json(capsys, "eval", tiny_dataset, "--rig", rig_file, "--texcoords", slid_sheet, "--poses", "0,4", "--quiet")
    assert result["num_images"] == 4 and set(result["per_camera"]) == {"a", "b"}
    assert result["ratio"] > 1 and result["ratio_same_chart"] > 1
    assert result == json.loads(json.dumps(evaluate(tiny_dataset, rig_file, slid_sheet, poses=[0, 4], progress=False,
                                                    ctx=gl).to_json()))


@pytest.mark.gl
def test_triangulate_json(gl, tiny_dataset, rig_file, slid_sheet, tmp_path, capsys):
    out = tmp_path / "rec"
    result = run_json(capsys, "triangulate", tiny_dataset, "--rig", rig_file, "--texcoords", slid_sheet, "--pose", 2,
                      "--out", out, "--quiet")
    assert result["pose"] == 2 and 0 < result["num_triangulated"] <= result["num_vertices"] == 480
    assert result == json.loads((out / "report.json").read_text())
    assert (out / "reconstruction.ply").exists()


@pytest.mark.slow
@pytest.mark.gl
def test_train_json_then_predict(gl, tiny_dataset, slid_sheet, tmp_path, capsys):
    pytest.importorskip("torch")
    from mvtex.data.dataset import load_dataset
    from mvtex.data.texcoords import open_texcoords
    from mvtex.tsnn.predict import load_model, predict_displacements

    out = tmp_path / "model"
    result = run_json(capsys, "train", tiny_dataset, "--texcoords", slid_sheet, "--cameras", "a", "--out", out,
                      "--arch", "paper", "--epochs", 1, "--resolution", 32, "--device", "cpu", "--quiet")
    assert result["camera"] == "a" and result["resolution"] == 32
    code, _, err = run(capsys, "predict", tiny_dataset, "--model", out, "--out", tmp_path / "pred", "--poses", "1,5",
                       "--quiet")
    assert code == 0, err
    pred = open_texcoords(tmp_path / "pred", 480)
    assert pred.cameras == ["a"] and pred.poses == [1, 5] and pred.source == "tsnn"
    ds = load_dataset(tiny_dataset)
    expected = predict_displacements(load_model(out), np.asarray(ds.poses)[[1, 5]], pred.uv)
    assert np.allclose(pred.displacement("a", 5), expected[1], atol=1e-6)


def test_import_through_main(tmp_path, capsys):
    from helpers import grid_mesh, wave, write_obj

    from mvtex.data.dataset import load_dataset

    faces, uv, rest = grid_mesh(6, 5)
    for k in range(2):
        write_obj(tmp_path / f"gt_{k}.obj", wave(rest, 0.01, k), uv, faces)
        write_obj(tmp_path / f"inf_{k}.obj", wave(rest, 0.003, k), uv, faces)
    code, out, err = run(capsys, "import", "--out", tmp_path / "ds", "--gt", tmp_path / "gt_*.obj", "--inferred",
                         tmp_path / "inf_*.obj", "--name", "sheet", "--quiet")
    assert code == 0, err
    ds = load_dataset(tmp_path / "ds")
    assert ds.name == "sheet" and ds.num_poses == 2 and np.array_equal(ds.faces, faces)
    assert np.allclose(ds.gt[1], wave(rest, 0.01, 1), atol=1e-6)
    assert np.allclose(ds.inferred[0], wave(rest, 0.003, 0), atol=1e-6)


@pytest.mark.gl
def test_bench_json_both_paths_agree(gl, tiny_dataset, rig_file, capsys):
    """`bench` claims the raster path and the Embree ray-cast path agree: d to 1e-5 uv on
    vertices both assign, the same assigned flags almost everywhere."""
    pytest.importorskip("embreex")
    result = run_json(capsys, "bench", tiny_dataset, "--rig", rig_file, "--poses", "0:2", "--workers", 1, "--quiet")
    assert result["jobs"] == 4 and result["cameras"] == ["a", "b"]
    assert result["agreement"]["displacement"] >= 0.999
    assert result["agreement"]["assigned_flags"] >= 0.99
    assert result["sliding"]["raster"]["jobs_per_s"] > 0 and result["machine"]["gl_renderer"]


# -- options of sliding ------------------------------------------------------------------------

def _two_chart_scene():
    from helpers import two_chart_sheet

    faces, uv, rest, face_chart = two_chart_sheet()
    camera = look_at("c", (0.0, 0.05, 1.2), (0, 0, 0), width=160, height=120, focal=260.0)
    # Slid sideways across the seam: near x = 0 the rays of one chart's vertices hit the other chart.
    inferred = rest + [0.02, 0.0, 0.01]
    return faces, uv, rest, inferred, camera


@pytest.mark.gl
def test_cross_chart_keeps_hits_on_the_other_chart(gl):
    from mvtex.data.mesh import subdivide, uv_charts
    from mvtex.sliding.options import SlideOptions
    from mvtex.sliding.pose import slide_pose

    faces, uv, gt, inferred, camera = _two_chart_scene()
    sub = subdivide(faces, len(uv), 0)
    chart = uv_charts(faces, len(uv))
    results = {}
    for cross in (False, True):
        results[cross] = slide_pose(gt, inferred, faces, uv, camera, sub, SlideOptions(subdiv=0, cross_chart=cross),
                                    ctx=gl)
    (d0, a0), (d1, a1) = results[False], results[True]
    # The charts sit 0.1 apart in u: a hit on the other chart shows as |d_u| > 0.1.
    jumped = a1 & (np.abs(d1[:, 0]) > 0.1)
    assert jumped.sum() >= 5 and np.all(a0 <= a1)
    assert not np.any(a0 & (np.abs(d0[:, 0]) > 0.1))
    # Kept across charts exactly where the default unassigns, and the same d elsewhere.
    assert np.array_equal(a1 & ~a0, jumped)
    assert np.array_equal(d0[a0], d1[a0])
    # Independent check of "the other chart": the jumped vertices are chart 0's, and their
    # rays meet the plane z = 0 of gt beyond the last chart-0 column (x = +half a grid step).
    origin = camera.center
    t = -origin[2] / (inferred[:, 2] - origin[2])
    x_hit = origin[0] + t * (inferred[:, 0] - origin[0])
    assert np.all(chart[jumped] == chart[np.argmin(gt[:, 0])])
    assert np.all(x_hit[jumped] > 0.6 / 23 / 2)


@pytest.mark.gl
def test_max_displacement_unassigns_exactly_the_large_ones(gl):
    from mvtex.data.mesh import subdivide
    from mvtex.sliding.options import SlideOptions
    from mvtex.sliding.pose import slide_pose

    faces, uv, gt, inferred, camera = _two_chart_scene()
    sub = subdivide(faces, len(uv), 0)
    d, a = slide_pose(gt, inferred, faces, uv, camera, sub, SlideOptions(subdiv=0), ctx=gl)
    norm = np.linalg.norm(d, axis=1)
    limit = float(np.median(norm[a]))
    d_lim, a_lim = slide_pose(gt, inferred, faces, uv, camera, sub, SlideOptions(subdiv=0, max_displacement=limit),
                              ctx=gl)
    assert np.array_equal(a_lim, a & (norm <= limit))
    assert 0 < a_lim.sum() < a.sum()
    assert np.array_equal(d_lim[a_lim], d[a_lim])
