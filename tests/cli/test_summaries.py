"""What the commands print and record: triangulate's summary leads with the RMSE; bench's
text without --json; a finished slide returns at once; texcoord sets record their rig and
--rig defaults to it."""

from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest
from helpers import run


@pytest.mark.gl
def test_finished_slide_returns_at_once_and_records_its_rig(tmp_path, tiny_dataset, rig_file, front_rig, gl, capsys):
    from mvtex.data.rig import load_rig

    out = tmp_path / "ts"
    code, first, err = run(capsys, "slide", tiny_dataset, "--rig", rig_file, "--poses", "0,2", "--out", out, "--quiet")
    assert code == 0, err and first.startswith("wrote")
    recorded = load_rig(out / "rig.yaml")
    for cam in front_rig:
        assert np.allclose(recorded[cam.name].K, cam.K) and np.allclose(recorded[cam.name].t, cam.t)
    stamp = {p: os.stat(p).st_mtime_ns for p in out.rglob("*.npy")}
    code, again, err = run(capsys, "slide", tiny_dataset, "--rig", rig_file, "--poses", "0,2", "--out", out)
    assert code == 0 and "is complete" in again and "nothing to do" in again
    assert {p: os.stat(p).st_mtime_ns for p in out.rglob("*.npy")} == stamp  # nothing rewritten
    code, js, _ = run(capsys, "slide", tiny_dataset, "--rig", rig_file, "--poses", "0,2", "--out", out, "--json")
    assert json.loads(js)["complete_before"] is True
    # Other options: slid again.
    code, other, err = run(capsys, "slide", tiny_dataset, "--rig", rig_file, "--poses", "0,2", "--out", out,
                           "--subdiv", "0", "--quiet")
    assert code == 0 and other.startswith("wrote")
    assert json.loads((out / "texcoords.json").read_text())["subdiv"] == 0


@pytest.mark.slow
@pytest.mark.gl
def test_rig_defaults_to_the_sets_rig(tmp_path, tiny_dataset, rig_file, gl, capsys):
    out = tmp_path / "ts"
    assert run(capsys, "slide", tiny_dataset, "--rig", rig_file, "--poses", "1", "--out", out, "--quiet")[0] == 0
    code, with_rig, _ = run(capsys, "eval", tiny_dataset, "--rig", rig_file, "--texcoords", out, "--json", "--quiet")
    code2, without, err = run(capsys, "eval", tiny_dataset, "--texcoords", out, "--json", "--quiet")
    assert code == code2 == 0, err
    assert json.loads(with_rig) == json.loads(without)
    code, _, err = run(capsys, "render", tiny_dataset, "--texcoords", out, "--pose", 1, "--out", tmp_path / "r",
                       "--quiet")
    assert code == 0, err
    # No rig recorded and none given: the usual one-line error.
    bare = tmp_path / "bare"
    shutil.copytree(out, bare)
    (bare / "rig.yaml").unlink()
    code, _, err = run(capsys, "eval", tiny_dataset, "--texcoords", bare, "--quiet")
    assert code == 2 and "--rig" in err and len(err.strip().splitlines()) == 1
    code, _, err = run(capsys, "render", tiny_dataset, "--pose", 1, "--out", tmp_path / "r2", "--quiet")
    assert code == 2 and "required: --rig" in err


@pytest.mark.slow
@pytest.mark.gl
def test_triangulate_summary_leads_with_the_rmse(tmp_path, sheet_set, capsys):
    dataset, rig, tc = sheet_set
    code, text, err = run(capsys, "triangulate", dataset, "--rig", rig, "--texcoords", tc, "--pose", 2, "--out",
                          tmp_path / "rec", "--quiet")
    assert code == 0, err
    report = json.loads((tmp_path / "rec" / "report.json").read_text())
    first = text.splitlines()[0]
    assert first.startswith("RMSE vs gt, inferred -> reconstructed")
    tri, all_ = report["rmse_triangulated_m"], report["rmse_m"]
    assert f"{tri['inferred'] * 1e3:.2f} mm -> {tri['reconstructed'] * 1e3:.2f} mm" in first
    assert f"{all_['inferred'] * 1e3:.2f} mm -> {all_['reconstructed'] * 1e3:.2f} mm" in first
    assert first.index("triangulated") < first.index("all vertices")
    scales = json.loads((tmp_path / "rec" / "comparison.json").read_text())["scales"]
    assert scales["error"]["unit"] == "mm" and scales["error"]["log"] is True


def test_bench_summary_is_text_and_json_only_with_json():
    from mvtex.apps.bench import BenchResult

    result = BenchResult(jobs=8, poses=4, cameras=["a", "b"], subdiv=1, num_vertices=100, image_size=[160, 120],
                         sliding={"raster": {"jobs_per_s": 40.0, "seconds": 0.2},
                                  "raycast": {"jobs_per_s": 10.0, "seconds": 0.8}, "raster_workers": None},
                         body=None, speedup=4.0, agreement={"displacement": 0.999, "assigned_flags": 1.0},
                         eval={"images_per_s": 30.0}, machine={"cpu_count": 2, "gl_renderer": "llvmpipe"})
    text = result.summary()
    assert text.splitlines()[0].startswith("sliding: 40.0 jobs/s (raster")
    assert "4.00x" in text and "{" not in text


@pytest.mark.slow
def test_progress_reaches_stderr_and_quiet_silences_it(tmp_path, capsys):
    code, out, err = run(capsys, "synth", "--out", tmp_path / "d", "--num-poses", 10, "--garment", "skirt")
    assert code == 0 and "synth skirt" in err and "20/20" in err
    code, out, err = run(capsys, "synth", "--out", tmp_path / "e", "--num-poses", 10, "--garment", "skirt", "--quiet")
    assert code == 0 and "synth skirt" not in err


def test_lbfgs_progress_counts_steps_to_the_end():
    torch = pytest.importorskip("torch")
    from mvtex.tsnn.lbfgs import minimise

    target = torch.tensor([[1.0, -2.0], [0.5, 3.0], [0.0, 0.0]], dtype=torch.float64)

    def objective(x, rows):
        diff = x - target[rows]
        return (diff ** 2).sum(1), 2 * diff

    calls = []
    minimise(objective, torch.zeros(3, 2, dtype=torch.float64), 10, progress=lambda d, t: calls.append((d, t)))
    done = [d for d, _ in calls]
    assert done == sorted(done) and calls[-1] == (30, 30) and len(calls) > 1
