"""The benchmark scripts behind the tables of docs/ run (small sizes)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"
pytestmark = pytest.mark.gl


def load(name: str):
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_table_recon_small(tmp_path):
    from mvtex.recon.consensus import OBSERVATION_REASONS

    summary = load("table_recon").main([str(tmp_path), "--garments", "shirt", "--rigs", "stereo", "--num-poses", "10",
                                        "--poses", "0:2", "--subdiv", "0", "--recon", "max_stretch=off",
                                        "--json", str(tmp_path / "out.json")])
    assert summary["options"]["max_stretch"] is None and summary["slide"]["subdiv"] == 0
    (row,) = summary["rows"]
    assert (row["garment"], row["rig"], row["texcoords"]) == ("shirt", "stereo", "TS")
    assert row["poses"] == [0, 1] and 0 < row["triangulated_share"] < 1
    assert row["rmse_triangulated_mm"]["reconstructed"] < row["rmse_triangulated_mm"]["inferred"]
    assert row["ratio_triangulated"]["worst"] <= row["ratio_triangulated"]["median"]
    assert set(row["rejected_observations"]) == set(OBSERVATION_REASONS)
    assert row["rejected_observations"]["stretched_triangle"] == 0  # the test is off
    assert summary["table"].count("| shirt | stereo | TS |") == 2
    assert (tmp_path / "out.json").exists()


def test_material_where_splits_eval_s_error(sheet_set, tmp_path):
    """Its classes of pixels on the one-chart flat sheet seen from the front: no other chart,
    no inside; the openings are the sheet's border, at closed-form distances; with a
    distance that takes in everything, every pixel and all the error is near an opening."""
    from mvtex.data.dataset import load_dataset

    data, rig_file, texcoords = sheet_set
    where = load("material_where")
    ds = load_dataset(data)
    x, y = np.asarray(ds.rest, np.float64)[:, 0], np.asarray(ds.rest, np.float64)[:, 1]
    expected = np.minimum(x.max() - np.abs(x), y.max() - np.abs(y))
    assert np.allclose(where.opening_distance(ds), expected, atol=1e-6)
    out = where.main([str(data), str(texcoords), "--rig", str(rig_file), "--picture", str(tmp_path / "where.png")])
    classes = out["classes"]
    assert classes["another chart"]["pixel_share"] == 0 and classes["another chart"]["error_share"] == 0
    assert classes["inside shown"]["pixel_share"] == 0
    assert 0 < classes["near an opening"]["pixel_share"] < 1
    everything = where.main([str(data), str(texcoords), "--rig", str(rig_file), "--near-opening", "1"])["classes"]
    assert everything["near an opening"]["pixel_share"] == 1
    assert everything["near an opening"]["error_share"] == pytest.approx(1)
    assert (tmp_path / "where.png").stat().st_size > 0


@pytest.mark.slow
def test_body_hidden_counts_what_the_body_hides(tmp_path):
    """One pose of the worn T-shirt, stereo and the cameras into its openings: the body
    hides many vertices per Embree, `slide` assigns none of them."""
    pytest.importorskip("embreex")
    from mvtex.synth.generate import SynthOptions, write_synth

    write_synth(tmp_path / "shirt", SynthOptions(num_poses=3, seed=2))
    out = load("body_hidden").main([str(tmp_path / "shirt"), "--rigs", "stereo", "--openings", "--poses", "0",
                                    "--subdiv", "0", "--json", str(tmp_path / "rows.json")])
    assert [(r["rig"], r["jobs"]) for r in out["rows"]] == [("stereo", 2), ("openings", 4)]
    for row in out["rows"]:
        assert row["hidden"] > 1000 and row["assigned_total"] > 1000
        assert row["assigned"] == 0
    assert (tmp_path / "rows.json").exists()


@pytest.mark.slow
def test_table_corrector_small(tmp_path):
    """The five columns on a 14-pose shirt with the stereo rig: every number there, the
    corrector's ratio the one computed here from the files, the merged table the same."""
    import sys

    sys.path.insert(0, str(BENCHMARKS))  # it reads table_recon beside it
    from mvtex.data.dataset import load_dataset

    table = load("table_corrector")
    summary = table.main([str(tmp_path), "--garments", "shirt", "--num-poses", "14", "--rigs", "stereo",
                          "--json", str(tmp_path / "out.json")])
    (row,) = summary["rows"]
    assert row["train_poses"] == 12 and row["split"] == "test"
    assert set(row["stereo"]) >= set(table.COLUMNS) and row["stereo"]["num_images"] == 2 * len(row["poses"])
    rec = row["rigs"]["stereo"]
    assert set(rec) >= set(table.COLUMNS[1:])
    source = load_dataset(tmp_path / "data" / "shirt14")
    fixed = load_dataset(tmp_path / "work" / "shirt14" / "corrected")

    def rmse(a, b):
        return np.sqrt(np.mean(np.sum((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2, axis=1)))

    expected = [rmse(source.inferred[k], source.gt[k]) / rmse(fixed.inferred[k], source.gt[k]) for k in row["poses"]]
    assert rec["corrector"]["per_pose"] == pytest.approx(expected, rel=1e-9)
    assert table.merge([tmp_path / "out.json"]) == summary["table"]
    # The same set through --data, without the plain path: the same numbers, no gp column.
    again = table.main([str(tmp_path), "--data", str(tmp_path / "data" / "shirt14"), "--no-plain", "--no-stereo",
                        "--rigs", "stereo"])
    (other,) = again["rows"]
    assert other["garment"] == "shirt" and other["poses"] == row["poses"]
    assert "gp" not in other["rigs"]["stereo"]
    for column in table.COLUMNS[1:]:
        if column != "gp":
            assert other["rigs"]["stereo"][column]["per_pose"] == rec[column]["per_pose"]
