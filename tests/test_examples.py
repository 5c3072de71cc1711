"""The examples a user reads first must run (small sizes); the benchmark scripts behind the
tables of docs/results run at small sizes too."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "examples"
BENCHMARKS = ROOT / "benchmarks"
pytestmark = pytest.mark.gl


def load(name: str, folder: Path = EXAMPLES):
    spec = importlib.util.spec_from_file_location(name, folder / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_quickstart(tmp_path, gl):
    result = load("quickstart").main(tmp_path, 12)
    assert result["eval"].ratio > 1.0 and result["eval"].ratio_material > 1.0
    r = result["reconstruction"]
    assert r.rmse_triangulated_m.reconstructed < r.rmse_triangulated_m.inferred / 3
    assert (tmp_path / "reconstruction" / "colmap" / "points3D.bin").exists()


def test_quickstart_uses_the_public_api_only():
    import ast

    tree = ast.parse((EXAMPLES / "quickstart.py").read_text())
    modules = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    modules |= {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    assert modules == {"sys", "pathlib", "mvtex"}


@pytest.mark.slow
def test_own_data_import(tmp_path, gl):
    module = load("own_data")
    gt_glob, inferred_glob = module.demo_sequence(tmp_path, num_poses=3)
    tc = module.main(gt_glob, inferred_glob, tmp_path / "out")
    assert (tc / "texcoords.json").exists()


@pytest.mark.slow
def test_ar_preview(tmp_path, gl):
    import imageio.v3 as iio
    import numpy as np

    preview = load("ar_preview").main(tmp_path, 12)
    for eye in ("left", "right"):
        inferred, sliding = preview.eyes[eye].ssim
        assert 0 < inferred < sliding <= 1  # sliding shows the gt cloth's texture
    stereo = iio.imread(tmp_path / "preview" / "stereo.png")
    assert stereo.shape[:2] == (512, 2 * 512)  # left | right, each a 512x512 stereo camera
    left, right = stereo[:, :512].astype(int), stereo[:, 512:].astype(int)
    assert np.abs(left - right).mean() > 0.5  # the eyes are 6.4 cm apart: different pictures


def test_make_rigs_matches_shipped_rigs(tmp_path):
    import numpy as np

    from mvtex.data.rig import builtin_rig_file, load_rig

    rigs = load("make_rigs").rigs()
    for name, rig in rigs.items():
        shipped = load_rig(builtin_rig_file(name))
        assert shipped.names == rig.names
        for a, b in zip(shipped, rig):
            assert np.allclose(a.R, b.R) and np.allclose(a.t, b.t) and np.allclose(a.K, b.K)


def test_fill_laplacian_compares_both_operators(tmp_path, gl, tiny_dataset, front_rig):
    from mvtex.data.rig import save_rig

    save_rig(front_rig, tmp_path / "rig.yaml")
    result = load("fill_laplacian", BENCHMARKS).main(str(tiny_dataset), str(tmp_path / "rig.yaml"), "0,3")
    assert set(result) == {"cotan", "intrinsic"}
    for r in result.values():
        assert r["images"] == 4 and r["held_out_vertices"] > 0
        assert 0 <= r["held_out_rmse_uv"] < 0.01 and r["ratio_same_chart"] > 1


@pytest.mark.slow
def test_defaults_study_small(tmp_path, gl):
    module = load("defaults_study", BENCHMARKS)
    rows = module.study(tmp_path, 10, ["shirt", "skirt"], ["stereo"], only=["defaults", "break ratio 4"])
    assert [(r["garment"], r["candidate"]) for r in rows] == [("shirt", "defaults"), ("shirt", "break ratio 4"),
                                                             ("skirt", "defaults"), ("skirt", "break ratio 4")]
    for row in rows:
        for subdiv in ("subdiv0", "subdiv1"):
            r = row[subdiv]["stereo"]
            assert r["num_images"] == 2
            # Sliding moves the shown material towards gt on both garments.
            assert r["material_mm"]["texcoords"] < r["material_mm"]["inferred"]
    table = module.markdown(rows, ["stereo"])
    assert table.count("| skirt |") == 2 and "TS+1 material mm" in table


@pytest.mark.slow
def test_paper_scale_runs_small(tmp_path):
    table = load("paper_scale", BENCHMARKS).main(tmp_path / "work", poses=10, trapezoid_poses=1, workers=(1,))
    rows = [line for line in table.splitlines() if line.startswith("| slide")]
    assert len(rows) == 2 and all(float(row.split("|")[4]) > 0 for row in rows)
    assert (tmp_path / "work" / "stereo_w1" / "texcoords.json").exists()
    with pytest.raises(SystemExit, match="exists"):
        load("paper_scale", BENCHMARKS).main(tmp_path / "work", poses=10, trapezoid_poses=1, workers=(1,))


@pytest.mark.parametrize("path", sorted([*EXAMPLES.glob("*.py"), *BENCHMARKS.glob("*.py")]),
                         ids=lambda p: f"{p.parent.name}/{p.stem}")
def test_every_example_imports_names_that_exist(path):
    """Every `from mvtex... import name` in an example or a benchmark (at any depth) names
    something real."""
    import ast
    import importlib

    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "mvtex":
            module = importlib.import_module(node.module)
            for alias in node.names:
                assert hasattr(module, alias.name) or importlib.util.find_spec(f"{node.module}.{alias.name}"), \
                    f"{path.name}: {node.module} has no {alias.name}"


def test_profile_job_times_every_step(tmp_path, gl, tiny_dataset, front_rig):
    """Each wrapped function is the one the raster path calls (its timer runs), and the
    remainders (hit search and displacement step minus their timed calls) are not negative:
    a renamed or re-imported step would leave its timer at 0 or count time twice."""
    from mvtex.data.rig import save_rig

    save_rig(front_rig, tmp_path / "rig.yaml")
    report, ms = load("profile_job", BENCHMARKS).main(str(tiny_dataset), str(tmp_path / "rig.yaml"), "0:2", 1)
    for step in ("raster", "occluder", "first_hits", "inside", "fill", "solve"):
        assert ms[step] > 0, step
    assert ms["solve"] < ms["fill"] and all(value >= 0 for value in ms["rows"])
    assert report.count("\n| ") == 1 + 6  # the header and one row per step
