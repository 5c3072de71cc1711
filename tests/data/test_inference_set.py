"""Inference sets (DESIGN §4): a dataset without ground truth, written, read and refused
where gt is needed, with a typed error that names the dataset."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import grid_mesh, wave


def _frames(k: int = 3):
    faces, uv, rest = grid_mesh(8, 6)
    inferred = np.stack([wave(rest, 0.004, p) for p in np.linspace(0, 1, k)]).astype(np.float32)
    poses = np.linspace(-1, 1, 2 * k, dtype=np.float32).reshape(k, 2)
    return faces, uv, rest, inferred, poses


def test_save_dataset_without_gt_writes_an_inference_set(tmp_path):
    import mvtex
    from mvtex.data.dataset import load_dataset, reference_shape, reference_shape_source, save_dataset

    faces, uv, rest, inferred, poses = _frames()
    save_dataset(tmp_path / "frames", faces=faces, uv=uv, gt=None, inferred=inferred, poses=poses, name="frames")
    assert not (tmp_path / "frames" / "gt.npy").exists()
    meta = json.loads((tmp_path / "frames" / "dataset.json").read_text())
    assert meta["ground_truth"] is False and meta["num_poses"] == 3
    ds = load_dataset(tmp_path / "frames")
    assert not ds.has_gt and ds.num_poses == 3 and ds.num_vertices == len(uv)
    with pytest.raises(mvtex.NoGroundTruthError, match="frames.*no ground truth.*gt.npy") as caught:
        ds.gt  # noqa: B018 (the property is the check)
    assert isinstance(caught.value, mvtex.InputError) and caught.value.path == str(tmp_path / "frames")
    # Without rest, the reference shape is the first inferred frame (exactly).
    assert reference_shape_source(ds) == "inferred[0]"
    np.testing.assert_array_equal(reference_shape(ds), inferred[0].astype(np.float64))
    # A dataset with gt says so by leaving the key out (older datasets stay valid).
    save_dataset(tmp_path / "full", faces=faces, uv=uv, gt=inferred, inferred=inferred, poses=poses, rest=rest)
    assert "ground_truth" not in json.loads((tmp_path / "full" / "dataset.json").read_text())
    full = load_dataset(tmp_path / "full")
    assert full.has_gt and np.array_equal(full.gt, inferred)


def test_inference_set_files_must_agree(tmp_path):
    from mvtex.data.dataset import load_dataset, save_dataset
    from mvtex.util.errors import InputError

    faces, uv, rest, inferred, poses = _frames()
    save_dataset(tmp_path / "f", faces=faces, uv=uv, gt=None, inferred=inferred, poses=poses)
    np.save(tmp_path / "f" / "gt.npy", inferred)  # a gt.npy the header says is not there
    with pytest.raises(InputError, match="gt.npy.*ground_truth"):
        load_dataset(tmp_path / "f")
    (tmp_path / "f" / "gt.npy").unlink()
    meta = json.loads((tmp_path / "f" / "dataset.json").read_text())
    meta["ground_truth"] = "no"
    (tmp_path / "f" / "dataset.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="dataset.json.*ground_truth must be true or false"):
        load_dataset(tmp_path / "f")
    # An ordinary dataset without its gt.npy is a missing file, not an inference set.
    save_dataset(tmp_path / "g", faces=faces, uv=uv, gt=inferred, inferred=inferred, poses=poses)
    (tmp_path / "g" / "gt.npy").unlink()
    with pytest.raises(InputError, match="gt.npy"):
        load_dataset(tmp_path / "g")


def test_content_fingerprint_of_an_inference_set_follows_its_arrays(tmp_path):
    from mvtex.data.dataset import content_fingerprint, load_dataset, save_dataset

    faces, uv, rest, inferred, poses = _frames()
    save_dataset(tmp_path / "a", faces=faces, uv=uv, gt=None, inferred=inferred, poses=poses)
    moved = inferred.copy()
    moved[1, 0, 2] += 1e-3
    save_dataset(tmp_path / "b", faces=faces, uv=uv, gt=None, inferred=moved, poses=poses)
    save_dataset(tmp_path / "c", faces=faces, uv=uv, gt=None, inferred=inferred, poses=poses + 1)
    prints = {content_fingerprint(load_dataset(tmp_path / k)) for k in "abc"}
    assert len(prints) == 3


@pytest.mark.gl
def test_stages_that_need_gt_refuse_an_inference_set(tmp_path, front_rig, gl):
    from mvtex.apps.bench import run_bench
    from mvtex.data.dataset import load_dataset, save_dataset
    from mvtex.evaluation.evaluate import evaluate
    from mvtex.sliding.dataset import slide_dataset
    from mvtex.sliding.options import SlideOptions
    from mvtex.util.errors import NoGroundTruthError

    faces, uv, rest, inferred, poses = _frames()
    save_dataset(tmp_path / "frames", faces=faces, uv=uv, gt=None, inferred=inferred, poses=poses)
    ds = load_dataset(tmp_path / "frames")
    with pytest.raises(NoGroundTruthError, match="slide"):
        slide_dataset(ds, front_rig, tmp_path / "ts", poses=[0], options=SlideOptions(), workers=1, progress=False)
    with pytest.raises(NoGroundTruthError, match="eval"):
        evaluate(ds, front_rig, tmp_path / "nowhere", heatmaps=tmp_path / "heat", progress=False)
    with pytest.raises(NoGroundTruthError, match="bench"):
        run_bench(ds, front_rig, poses=[0], workers=1, progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames"]  # nothing written
