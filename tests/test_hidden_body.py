"""A body that hides nothing changes nothing: a box behind the sheet, covered by it in every
camera, leaves slide, eval (but for its body share), triangulate and views bit for bit
what they are without a body (the body is in every depth test and never wins one)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

pytestmark = pytest.mark.gl


@pytest.fixture(scope="module")
def pair(tmp_path_factory, tiny_dataset):
    """The tiny sheet dataset, and the same with a box body 5-10 cm behind it."""
    from mvtex.data.dataset import load_dataset, save_dataset

    bare = load_dataset(tiny_dataset)
    box = trimesh.creation.box(extents=(0.2, 0.16, 0.05),
                               transform=trimesh.transformations.translation_matrix((0.0, 0.0, -0.075)))
    body = np.repeat(np.asarray(box.vertices, np.float32)[None], bare.num_poses, axis=0)
    path = tmp_path_factory.mktemp("hidden") / "sheet"
    save_dataset(path, faces=bare.faces, uv=bare.uv, gt=np.asarray(bare.gt), inferred=np.asarray(bare.inferred),
                 poses=np.asarray(bare.poses), name="sheet", rest=bare.rest, split=bare.split,
                 body_faces=np.asarray(box.faces, np.int32), body=body)
    worn = load_dataset(path)
    assert worn.body is not None and bare.body is None
    return bare, worn


def _slid(dataset, rig, out, gl):
    from mvtex.data.texcoords import open_texcoords
    from mvtex.sliding.dataset import slide_dataset
    from mvtex.sliding.options import SlideOptions

    slide_dataset(dataset, rig, out, poses=[0, 3], options=SlideOptions(subdiv=1), progress=False, ctx=gl)
    return open_texcoords(out, dataset.num_vertices)


@pytest.mark.slow
def test_a_hidden_body_changes_no_output(pair, front_rig, tmp_path, gl):
    from mvtex.evaluation.evaluate import evaluate
    from mvtex.recon.pose import triangulate_pose
    from mvtex.views.novel import novel_views

    bare, worn = pair
    sets = {name: _slid(ds, front_rig, tmp_path / f"tc_{name}", gl) for name, ds in (("bare", bare), ("worn", worn))}
    for camera in front_rig.names:
        for k in (0, 3):
            assert np.array_equal(sets["bare"].displacement(camera, k), sets["worn"].displacement(camera, k))
            assert np.array_equal(sets["bare"].assigned(camera, k), sets["worn"].assigned(camera, k))
    assert sets["bare"].assigned("a", 0).mean() > 0.5  # the sheet is seen and slid

    ev = {name: evaluate(ds, front_rig, sets[name], progress=False, ctx=gl).to_json()
          for name, ds in (("bare", bare), ("worn", worn))}
    assert ev["bare"]["body_share"] is None
    assert ev["worn"]["body_share"]["mean"] == 0.0
    def without_share(result):
        out = {k: v for k, v in result.items() if k != "body_share"}
        out["per_camera"] = {c: without_share(v) for c, v in result.get("per_camera", {}).items()}
        return out

    assert without_share(ev["bare"]) == without_share(ev["worn"])
    assert ev["bare"]["ratio_material"] > 2  # and it measured something

    rec = {name: triangulate_pose(ds, front_rig, sets[name], 3, None, progress=False, ctx=gl).to_json()
           for name, ds in (("bare", bare), ("worn", worn))}
    assert rec["worn"]["rejected_observations"]["hidden_by_body"] == 0
    for key in ("num_triangulated", "rmse_m", "rmse_triangulated_m", "mean_reprojection_error_px", "rejected",
                "rejected_observations", "strain_energy"):
        assert rec["bare"][key] == rec["worn"][key], key

    from mvtex.data.texcoords import open_texcoords

    views = {}
    for name, ds in (("bare", bare), ("worn", worn)):
        novel_views(ds, front_rig, sets[name], tmp_path / f"views_{name}", [{"a": 0.5, "b": 0.5}], ["mid"],
                    progress=False)
        views[name] = open_texcoords(tmp_path / f"views_{name}", ds.num_vertices)
    for k in (0, 3):
        assert np.array_equal(views["bare"].displacement("mid", k), views["worn"].displacement("mid", k))
        assert np.array_equal(views["bare"].assigned("mid", k), views["worn"].assigned("mid", k))
