"""Per-pixel uv error against a computation from raster dumps done here, and heatmaps."""

from __future__ import annotations

import numpy as np
import pytest

from mvtex.dataset import load_dataset
from mvtex.metrics import evaluate, uv_error_image
from mvtex.raster import rasterize
from mvtex.texcoords import save_texcoords
from mvtex.viz import heatmap

pytestmark = pytest.mark.gl


def direct_sqrt_mse(gl, gt, faces, uv_gt, inf, faces_inf, tex, camera):
    """Rasterize both meshes, interpolate uv by hand from tri_id and bary, compare."""
    images = []
    for positions, f, t in ((gt, faces, uv_gt), (inf, faces_inf, tex)):
        r = rasterize(gl, positions, f, camera)
        mask = r.tri_id >= 0
        corners = np.asarray(t, np.float64)[np.asarray(f)[r.tri_id[mask]]]  # (k,3,2)
        uv_img = np.zeros(r.tri_id.shape + (2,))
        uv_img[mask] = (r.bary[mask][..., None].astype(np.float64) * corners).sum(axis=1)
        images.append((uv_img, mask))
    both = images[0][1] & images[1][1]
    e = np.linalg.norm(images[0][0][both] - images[1][0][both], axis=1)
    return e, both, np.sqrt(np.mean(e ** 2))


def test_baseline_and_texcoords_match_direct_computation(gl, tiny_dataset, front_rig, tmp_path):
    ds = load_dataset(tiny_dataset)
    poses = [1, 4]
    rng = np.random.default_rng(3)
    # A smooth, known displacement field per camera and pose (subdiv 0 set).
    disp = {c.name: (0.01 * np.sin(ds.uv[None, :, ::-1] * 6 + rng.uniform(0, 3, (len(poses), 1, 2)))).astype(np.float32)
            for c in front_rig}
    tc_path = save_texcoords(tmp_path / "tc", faces=ds.faces, uv=ds.uv, parent=np.stack([np.arange(480)] * 2, 1),
                             source="test", subdiv=0, poses=poses, displacement=disp,
                             assigned={c: np.ones(d.shape[:2], bool) for c, d in disp.items()})
    base, tex = {}, {}
    for cam in front_rig:
        base[cam.name], tex[cam.name] = [], []
        for row, k in enumerate(poses):
            gt, inf = np.asarray(ds.gt[k], np.float64), np.asarray(ds.inferred[k], np.float64)
            e, both, s = direct_sqrt_mse(gl, gt, ds.faces, ds.uv, inf, ds.faces, ds.uv, cam)
            err, s_lib = uv_error_image(gl, gt, ds.faces, ds.uv, inf, ds.faces, ds.uv, cam)
            assert np.array_equal(np.isfinite(err), both)
            assert np.allclose(err[both], e, atol=1e-6)
            assert abs(s_lib - s) < 1e-7 and s > 1e-4
            base[cam.name].append(s)
            tex[cam.name].append(direct_sqrt_mse(gl, gt, ds.faces, ds.uv, inf, ds.faces, ds.uv + disp[cam.name][row], cam)[2])
    heat = tmp_path / "heat"
    result = evaluate(tiny_dataset, front_rig, tc_path, heatmaps=heat, progress=False)
    all_b = [v for c in base.values() for v in c]
    all_t = [v for c in tex.values() for v in c]
    assert result["num_images"] == 4
    assert result["sqrt_mse"]["inferred"]["mean"] == pytest.approx(np.mean(all_b), rel=1e-5)
    assert result["sqrt_mse"]["inferred"]["std"] == pytest.approx(np.std(all_b), rel=1e-4, abs=1e-9)
    assert result["sqrt_mse"]["texcoords"]["mean"] == pytest.approx(np.mean(all_t), rel=1e-5)
    assert result["ratio"] == pytest.approx(np.mean(all_b) / np.mean(all_t), rel=1e-5)
    for name in ("a", "b"):
        per = result["per_camera"][name]
        assert per["num_images"] == 2
        assert per["sqrt_mse"]["inferred"]["mean"] == pytest.approx(np.mean(base[name]), rel=1e-5)
    assert sorted(p.name for p in heat.glob("*.png")) == ["pose_00001_a.png", "pose_00001_b.png",
                                                          "pose_00004_a.png", "pose_00004_b.png"]
    # A rig holding some of the set's cameras evaluates just those.
    only_b = evaluate(tiny_dataset, front_rig.select(["b"]), tc_path, progress=False)
    assert list(only_b["per_camera"]) == ["b"] and only_b["num_images"] == 2
    assert only_b["sqrt_mse"]["texcoords"]["mean"] == pytest.approx(np.mean(tex["b"]), rel=1e-5)


def test_sliding_beats_baseline_on_tiny_dataset(gl, tiny_dataset, front_rig, tmp_path):
    from mvtex.slide_jobs import slide_dataset
    from mvtex.sliding import SlideOptions

    tc = slide_dataset(tiny_dataset, front_rig, tmp_path / "ts", poses=[0, 3], options=SlideOptions(subdiv=1), progress=False)
    result = evaluate(tiny_dataset, front_rig, tc, progress=False)
    assert result["ratio"] > 2.0


def test_heatmap_colours():
    err = np.array([[0.0, 0.02, 0.04, 1.0, np.nan]])
    rgb = heatmap(err, vmax=0.04)
    assert rgb.shape == (1, 5, 3) and rgb.dtype == np.uint8
    r, g, b = rgb[0].astype(int).T
    assert b[0] > 100 and r[0] < 50          # 0 is blue
    assert r[2] > 100 and b[2] < 50          # vmax is red
    assert np.array_equal(rgb[0, 2], rgb[0, 3])  # saturates above vmax
    assert rgb[0, 4].max() < 60              # NaN is the dark background


def two_chart_sheet():
    """The wavy-sheet grid cut at x = 0 into two UV charts (seam vertices split): faces that
    touch x < 0 form chart 0 (u in [0, 0.45]), the rest chart 1 (u in [0.55, 1])."""
    from conftest import grid_mesh

    faces, uv, rest = grid_mesh(24, 20)
    in_chart0 = (rest[faces][:, :, 0] < 0).any(axis=1)
    chart1_vertices = np.unique(faces[~in_chart0])
    copy = {v: len(rest) + i for i, v in enumerate(chart1_vertices)}
    faces = faces.copy()
    faces[~in_chart0] = np.vectorize(copy.get)(faces[~in_chart0])
    positions = np.concatenate([rest, rest[chart1_vertices]])
    uv = np.concatenate([uv * [0.45, 1.0], uv[chart1_vertices] * [0.45, 1.0] + [0.55, 0.0]]).astype(np.float32)
    keep = np.unique(faces)  # drop chart-1-only originals that no face uses any more
    remap = np.full(len(positions), -1)
    remap[keep] = np.arange(len(keep))
    face_chart = (~in_chart0).astype(int)
    return remap[faces].astype(np.int32), uv[keep], positions[keep], face_chart


def test_same_chart_statistic_excludes_chart_boundaries(gl, front_rig, tmp_path):
    """Where the meshes show different charts the atlas distance is large; the same-chart
    statistic leaves exactly those pixels out (labels from the construction, not from mvtex)."""
    from mvtex.dataset import save_dataset

    faces, uv, rest, face_chart = two_chart_sheet()
    gt = rest[None].astype(np.float32)  # as stored in the dataset
    inferred = (gt + np.float32([0.012, 0.0, 0.0])).astype(np.float32)  # slid sideways: the chart boundary moves
    save_dataset(tmp_path / "d", faces=faces, uv=uv, gt=gt, inferred=inferred, poses=np.zeros((1, 1)))
    tc = save_texcoords(tmp_path / "tc", faces=faces, uv=uv, parent=np.stack([np.arange(len(uv))] * 2, 1),
                        source="test", subdiv=0, poses=[0],
                        displacement={c.name: np.zeros((1, len(uv), 2), np.float32) for c in front_rig},
                        assigned={c.name: np.ones((1, len(uv)), bool) for c in front_rig})
    result = evaluate(tmp_path / "d", front_rig, tc, progress=False)
    for cam in front_rig:
        rg, ri = rasterize(gl, gt[0], faces, cam), rasterize(gl, inferred[0], faces, cam)
        both = (rg.tri_id >= 0) & (ri.tri_id >= 0)
        same = both.copy()
        same[both] = face_chart[rg.tri_id[both]] == face_chart[ri.tri_id[both]]
        assert (both & ~same).sum() > 0
        e, _, s_all = direct_sqrt_mse(gl, gt[0], faces, uv, inferred[0], faces, uv, cam)
        err, _ = uv_error_image(gl, gt[0], faces, uv, inferred[0], faces, uv, cam)
        s_same = np.sqrt(np.mean(err[same].astype(np.float64) ** 2))
        per = result["per_camera"][cam.name]
        assert per["sqrt_mse"]["inferred"]["mean"] == pytest.approx(s_all, rel=1e-5)
        assert per["sqrt_mse_same_chart"]["inferred"]["mean"] == pytest.approx(s_same, rel=1e-5)
        assert s_same < 0.5 * s_all
