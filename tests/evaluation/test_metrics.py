"""Per-pixel uv error against a computation from raster dumps done here, and heatmaps."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import two_chart_sheet

from mvtex.data.dataset import load_dataset
from mvtex.data.texcoords import save_texcoords
from mvtex.evaluation.evaluate import evaluate
from mvtex.evaluation.uv import uv_error_image
from mvtex.render.pictures import heatmap
from mvtex.render.raster import rasterize

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
    assert result.num_images == 4
    assert result.sqrt_mse.inferred.mean == pytest.approx(np.mean(all_b), rel=1e-5)
    assert result.sqrt_mse.inferred.std == pytest.approx(np.std(all_b), rel=1e-4, abs=1e-9)
    assert result.sqrt_mse.texcoords.mean == pytest.approx(np.mean(all_t), rel=1e-5)
    assert result.ratio == pytest.approx(np.mean(all_b) / np.mean(all_t), rel=1e-5)
    for name in ("a", "b"):
        per = result.per_camera[name]
        assert per.num_images == 2
        assert per.sqrt_mse.inferred.mean == pytest.approx(np.mean(base[name]), rel=1e-5)
    assert sorted(p.name for p in heat.glob("*.png")) == ["pose_00001_a.png", "pose_00001_b.png",
                                                          "pose_00004_a.png", "pose_00004_b.png"]
    # A rig holding some of the set's cameras evaluates just those.
    only_b = evaluate(tiny_dataset, front_rig.select(["b"]), tc_path, progress=False)
    assert list(only_b.per_camera) == ["b"] and only_b.num_images == 2
    assert only_b.sqrt_mse.texcoords.mean == pytest.approx(np.mean(tex["b"]), rel=1e-5)


def test_sliding_beats_baseline_on_tiny_dataset(gl, tiny_dataset, front_rig, tmp_path):
    from mvtex.sliding.dataset import slide_dataset
    from mvtex.sliding.options import SlideOptions

    tc = slide_dataset(tiny_dataset, front_rig, tmp_path / "ts", poses=[0, 3], options=SlideOptions(subdiv=1), progress=False)
    result = evaluate(tiny_dataset, front_rig, tc, progress=False)
    assert result.ratio > 2.0


def test_heatmap_colours():
    err = np.array([[0.0, 0.02, 0.04, 1.0, np.nan]])
    rgb = heatmap(err, vmax=0.04)
    assert rgb.shape == (1, 5, 3) and rgb.dtype == np.uint8
    r, g, b = rgb[0].astype(int).T
    assert b[0] > 100 and r[0] < 50          # 0 is blue
    assert r[2] > 100 and b[2] < 50          # vmax is red
    assert np.array_equal(rgb[0, 2], rgb[0, 3])  # saturates above vmax
    assert rgb[0, 4].max() < 60              # NaN is the dark background


def test_same_chart_statistic_excludes_chart_boundaries(gl, front_rig, tmp_path):
    """Where the meshes show different charts the atlas distance is large; the same-chart
    statistic leaves exactly those pixels out (labels from the construction, not from mvtex)."""
    from mvtex.data.dataset import save_dataset

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
        per = result.per_camera[cam.name]
        assert per.sqrt_mse.inferred.mean == pytest.approx(s_all, rel=1e-5)
        assert per.sqrt_mse_same_chart.inferred.mean == pytest.approx(s_same, rel=1e-5)
        assert s_same < 0.5 * s_all


# -- material error ---------------------------------------------------------------------------

SHEET_SIZE = 0.6  # conftest.grid_mesh: uv = (xy + size/2) / size, rest in the z = 0 plane


@pytest.mark.slow
def test_material_error_is_scale_times_uv_error_on_flat_sheet(gl, tiny_dataset, front_rig, tmp_path):
    """Rest = flat sheet, uv = its positions / 0.6 m: every uv difference is a material
    difference of exactly 0.6 m per uv unit, so material error = 0.6 x uv error per pixel."""
    from mvtex.evaluation.material import MaterialMap, material_error_image

    ds = load_dataset(tiny_dataset)
    assert np.allclose(ds.uv * SHEET_SIZE - SHEET_SIZE / 2, ds.rest[:, :2], atol=1e-6)
    material_map = MaterialMap(ds.faces, ds.uv, ds.rest, ctx=gl)
    poses = [0, 2, 5]
    # Contract every camera's texcoords towards the centre: T_N stays on the sheet.
    disp = {c.name: np.stack([(-(0.06 + 0.03 * i) * (ds.uv - 0.5)).astype(np.float32) for i in range(len(poses))])
            for c in front_rig}
    for cam in front_rig:
        for row, k in enumerate(poses):
            gt, inf = np.asarray(ds.gt[k], np.float64), np.asarray(ds.inferred[k], np.float64)
            for tex in (ds.uv, ds.uv + disp[cam.name][row]):
                err_uv, s_uv = uv_error_image(gl, gt, ds.faces, ds.uv, inf, ds.faces, tex, cam)
                err_m, s_m = material_error_image(gl, gt, ds.faces, ds.rest, inf, ds.faces, tex, cam, material_map)
                both = np.isfinite(err_uv)
                assert np.array_equal(np.isfinite(err_m), both) and both.sum() > 1000
                assert np.allclose(err_m[both], SHEET_SIZE * err_uv[both], rtol=1e-4, atol=5e-6)  # float32 barycentrics
                assert s_m == pytest.approx(SHEET_SIZE * s_uv, rel=1e-4) and s_uv > 1e-3
    tc_path = save_texcoords(tmp_path / "tc", faces=ds.faces, uv=ds.uv, parent=np.stack([np.arange(480)] * 2, 1),
                             source="test", subdiv=0, poses=poses, displacement=disp,
                             assigned={c: np.ones(d.shape[:2], bool) for c, d in disp.items()})
    heat = tmp_path / "heat"
    result = evaluate(tiny_dataset, front_rig, tc_path, heatmaps=heat, progress=False)
    for part in (result, *result.per_camera.values()):
        for key in ("inferred", "texcoords"):
            expected = SHEET_SIZE * getattr(part.sqrt_mse, key).mean
            assert getattr(part.material_rmse_m, key).mean == pytest.approx(expected, rel=1e-4)
            assert getattr(part.material_rmse_m, key).std == pytest.approx(SHEET_SIZE * getattr(part.sqrt_mse, key).std,
                                                                        rel=1e-3, abs=1e-8)
        assert part.ratio_material == pytest.approx(part.ratio, rel=1e-4)
    # The heatmaps: a title, the uv row, a second row (material error in mm), then the legend,
    # between white gaps.
    from imageio.v3 import imread

    picture = imread(heat / "pose_00000_a.png")
    h = list(front_rig)[0].height
    white = np.flatnonzero((picture == 255).all(axis=(1, 2)))
    bands = np.split(np.arange(picture.shape[0]), white)
    heights = [len(b) - (1 if b[0] in white else 0) for b in bands]
    heights = [x for x in heights if x > 0]
    assert len(heights) == 4 and heights[1] == heights[2] == h, heights
    # One colour scale per measure in every picture: the colour bars of two images whose
    # errors differ (another pose, another camera, another contraction) are the same pixels.
    other = imread(heat / "pose_00005_b.png")
    assert other.shape == picture.shape
    bars = [p[heights[0] + 1:heights[0] + 2 * h + 6, -110:] for p in (picture, other)]
    assert np.array_equal(bars[0], bars[1])
    assert not np.array_equal(picture[heights[0] + 1:heights[0] + h, :-120], other[heights[0] + 1:heights[0] + h, :-120])


def test_material_error_matches_ray_cast_and_brute_force_uv_lookup(gl, front_rig):
    """A bent two-chart sheet whose charts have different uv scales and orientations:
    per-pixel material error against exact ray casts (trimesh) and a brute-force search of
    the containing uv triangle."""
    import trimesh
    from helpers import grid_mesh, wave

    from mvtex.evaluation.material import MaterialMap, material_error_image

    faces, uv, flat = grid_mesh(18, 14, 0.6)
    # Split the sheet at its middle column into two charts: the right half's vertices on
    # that column are duplicated (same positions, other uv).
    nx, ny = 18, 14
    idx = np.arange(nx * ny).reshape(ny, nx)
    mid = nx // 2
    copies = idx[:, mid]
    copy_of = {int(v): nx * ny + i for i, v in enumerate(copies)}
    right = flat[faces].mean(axis=1)[:, 0] > flat[copies[0], 0]
    faces = faces.copy()
    for f in np.flatnonzero(right):
        faces[f] = [copy_of.get(int(v), int(v)) for v in faces[f]]
    rest_flat = np.vstack([flat, flat[copies]])
    # Rest shape: the sheet bent around a vertical cylinder of radius 0.5 m (arc length x).
    R = 0.5
    rest = np.c_[R * np.sin(rest_flat[:, 0] / R), rest_flat[:, 1], R * (np.cos(rest_flat[:, 0] / R) - 1.0)]
    n = len(rest)
    is_right = np.zeros(n, bool)
    is_right[np.unique(faces[right])] = True
    uv = np.empty((n, 2))
    left_chart = ~is_right
    uv[left_chart] = 0.05 + 0.9 * (rest_flat[left_chart, :2] + [0.3, 0.3])  # 0.9 uv per m
    xr, yr = rest_flat[is_right, 0], rest_flat[is_right, 1]
    uv[is_right] = np.c_[0.62 + 0.55 * (yr + 0.3), 0.05 + 0.55 * xr]  # rotated, 0.55 uv per m
    assert uv.min() > 0 and uv.max() < 1
    gt = wave(rest, 0.012, 0.4)
    inferred = wave(rest, 0.004, 1.1) + [0.004, -0.003, 0.0]
    rng = np.random.default_rng(5)
    texcoords = uv + 0.004 * np.sin(7 * uv[:, ::-1] + rng.uniform(0, 3, 2))
    cam = list(front_rig)[1]
    err, rmse = material_error_image(gl, gt, faces, rest, inferred, faces, texcoords, cam, MaterialMap(faces, uv, rest, ctx=gl))

    # Independent: rays through pixel centres, exact hits, uv lookup by brute force.
    both = np.isfinite(err)
    from scipy.ndimage import binary_erosion

    interior = np.argwhere(binary_erosion(both, iterations=3))
    pick = interior[rng.choice(len(interior), 300, replace=False)]
    pixels = pick[:, ::-1].astype(np.float64)  # (u, v) = (column, row)
    dirs = (np.linalg.inv(cam.K) @ np.c_[pixels, np.ones(len(pixels))].T).T @ cam.R  # R^T d
    origin = -cam.R.T @ cam.t

    def hit(positions):
        """Nearest hit of every ray, brute force over all triangles (Moller-Trumbore, float64)."""
        a, b, c = (positions[faces[:, i]] for i in range(3))
        e1, e2 = b - a, c - a
        p = np.cross(dirs[:, None, :], e2[None])
        det = np.einsum("fj,rfj->rf", e1, p)
        s = origin - a
        with np.errstate(divide="ignore", invalid="ignore"):
            w1 = np.einsum("fj,rfj->rf", s, p) / det
            q = np.cross(s, e1)
            w2 = np.einsum("rj,fj->rf", dirs, q) / det
            t = np.einsum("fj,fj->f", e2, q)[None] / det
        ok = (w1 >= 0) & (w2 >= 0) & (w1 + w2 <= 1) & (t > 0)
        t = np.where(ok, t, np.inf)
        tri = np.argmin(t, axis=1)
        rows = np.arange(len(dirs))
        assert np.isfinite(t[rows, tri]).all()
        return tri, np.c_[1 - w1[rows, tri] - w2[rows, tri], w1[rows, tri], w2[rows, tri]]

    tri_g, bary_g = hit(gt)
    material_gt = np.einsum("kj,kjc->kc", bary_g, rest[faces[tri_g]])
    tri_i, bary_i = hit(inferred)
    shown_uv = np.einsum("kj,kjc->kc", bary_i, texcoords[faces[tri_i]])
    material_inf = np.full((len(pixels), 3), np.nan)
    for q, p in enumerate(shown_uv):
        b = trimesh.triangles.points_to_barycentric(np.c_[uv, np.zeros(n)][faces], np.tile([*p, 0.0], (len(faces), 1)))
        inside = np.flatnonzero(b.min(axis=1) >= -1e-12)
        if inside.size:
            material_inf[q] = b[inside[0]] @ rest[faces[inside[0]]]
    on_layout = np.isfinite(material_inf[:, 0])
    assert on_layout.sum() > 250
    expected = np.linalg.norm(material_inf - material_gt, axis=1)
    got = err[pick[:, 0], pick[:, 1]]
    assert np.abs(got[on_layout] - expected[on_layout]).max() < 2e-5
    assert expected[on_layout].mean() > 2e-3  # the case measures something


def test_material_map_clamps_off_layout_points_to_the_nearest_boundary_point(gl):
    from mvtex.evaluation.material import MaterialMap

    uv = np.array([[0.2, 0.2], [0.6, 0.2], [0.6, 0.6], [0.2, 0.6]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    rest = np.c_[(uv - 0.2) * 2.0, [0.0, 0.0, 1.0, 1.0]]  # 2 m per uv unit in x, y; z = v's ramp
    points = np.array([[0.3, 0.5], [0.9, 0.4], [0.1, 0.1], [0.59, 0.21]])
    got = MaterialMap(faces, uv, rest, resolution=256, ctx=gl)(points)
    nearest = np.clip(points, 0.2, 0.6)
    expected_xy = (nearest - 0.2) * 2.0
    assert np.allclose(got[:, :2], expected_xy, atol=1e-12)
    # z is linear inside each triangle: 0 at v = 0.2 on the lower right, 1 at the top.
    assert got[1, 2] == pytest.approx(0.5, abs=1e-12) and got[2, 2] == pytest.approx(0.0, abs=1e-12)


def test_dataset_without_rest_reports_null_material_error(gl, sheet, front_rig, tmp_path):
    from helpers import wave

    from mvtex.data.dataset import save_dataset

    faces, uv, rest = sheet
    gt = np.stack([wave(rest, 0.015, p) for p in (0.0, 1.0, 2.0)])
    path = save_dataset(tmp_path / "norest", faces=faces, uv=uv, gt=gt, inferred=gt * [1, 1, 0.3],
                        poses=np.eye(3), name="norest", split={"train": [0], "val": [1], "test": [2]})
    disp = {c.name: np.zeros((1, len(uv), 2), np.float32) for c in front_rig}
    tc = save_texcoords(tmp_path / "tc", faces=faces, uv=uv, parent=np.stack([np.arange(len(uv))] * 2, 1),
                        source="test", subdiv=0, poses=[2], displacement=disp,
                        assigned={c: np.ones(d.shape[:2], bool) for c, d in disp.items()})
    result = evaluate(path, front_rig, tc, progress=False)
    assert result.material_rmse_m is None and result.ratio_material is None
    assert result.per_camera["a"].material_rmse_m is None
    assert result.ratio == pytest.approx(1.0)


@pytest.mark.slow
def test_evaluate_equals_separate_renders_on_the_shirt(gl, tmp_path):
    """`evaluate` reads gt, baseline and texcoords from one pair raster; its numbers equal
    those of three separate renders (`uv_error_image`, `material_error_image`: the base
    inferred mesh with T_G, the subdivided one with T_N) on the built-in shirt (seams,
    openings), and so does a set whose faces are in another order (separate rasters)."""
    from mvtex.data.rig import as_rig
    from mvtex.data.texcoords import open_texcoords
    from mvtex.evaluation.material import MaterialMap, material_error_image
    from mvtex.sliding.dataset import slide_dataset
    from mvtex.sliding.options import SlideOptions
    from mvtex.synth.generate import SynthOptions, write_synth

    write_synth(tmp_path / "d", SynthOptions(num_poses=3, body=False))
    ds = load_dataset(tmp_path / "d")
    rig = as_rig("trapezoid12").select(["cam00", "cam05"])
    tc = open_texcoords(slide_dataset(ds, rig, tmp_path / "tc", poses=[1], options=SlideOptions(subdiv=1),
                                      progress=False, ctx=gl), ds.num_vertices)
    order = np.random.default_rng(0).permutation(len(tc.faces))
    shuffled = save_texcoords(tmp_path / "shuffled", faces=tc.faces[order], uv=tc.uv, parent=tc.parent, source="ts",
                              subdiv=1, poses=[1], displacement={c: tc.displacement(c, 1)[None] for c in rig.names},
                              assigned={c: np.ones((1, len(tc.uv)), bool) for c in rig.names})
    results = [evaluate(ds, rig, t, progress=False, ctx=gl) for t in (tc.path, shuffled)]
    material = MaterialMap(ds.faces, ds.uv, ds.rest, ctx=gl)
    gt, inferred = np.asarray(ds.gt[1], np.float64), np.asarray(ds.inferred[1], np.float64)
    for cam in rig:
        X, tex = tc.positions(inferred), tc.texcoords(cam.name, 1)
        s_b = uv_error_image(gl, gt, ds.faces, ds.uv, inferred, ds.faces, ds.uv, cam)[1]
        s_t = uv_error_image(gl, gt, ds.faces, ds.uv, X, tc.faces, tex, cam)[1]
        m_b = material_error_image(gl, gt, ds.faces, ds.rest, inferred, ds.faces, ds.uv, cam, material)[1]
        m_t = material_error_image(gl, gt, ds.faces, ds.rest, X, tc.faces, tex, cam, material)[1]
        for result in results:
            per = result.per_camera[cam.name]
            # Pixel centres exactly on an edge may fall either way between the renders.
            assert per.sqrt_mse.inferred.mean == pytest.approx(s_b, rel=2e-3)
            assert per.sqrt_mse.texcoords.mean == pytest.approx(s_t, rel=2e-3)
            assert per.material_rmse_m.inferred.mean == pytest.approx(m_b, rel=2e-3)
            assert per.material_rmse_m.texcoords.mean == pytest.approx(m_t, rel=2e-3)
            assert s_t > 1e-3 and m_t > 1e-4  # the case measures something


def test_material_error_on_assigned_triangles_matches_direct_computation(gl, tiny_dataset, front_rig, tmp_path):
    """The material error over fully assigned triangles, and their share of the pixels,
    against separate rasters read here: on the flat sheet, uv is rest xy scaled by 1/0.6, so
    a pixel's material error is 0.6 times its uv error."""
    ds = load_dataset(tiny_dataset)
    poses = [2]
    rng = np.random.default_rng(5)
    inner = np.all((ds.uv > 0.08) & (ds.uv < 0.92), axis=1)  # texcoords stay on the layout
    disp = {c.name: (0.01 * np.sin(ds.uv[None, :, ::-1] * 7 + rng.uniform(0, 3, (1, 1, 2))) * inner[None, :, None]
                     ).astype(np.float32) for c in front_rig}
    assigned = {c.name: rng.random((1, ds.num_vertices)) < 0.9 for c in front_rig}
    tc_path = save_texcoords(tmp_path / "tc", faces=ds.faces, uv=ds.uv, parent=np.stack([np.arange(480)] * 2, 1),
                             source="test", subdiv=0, poses=poses, displacement=disp, assigned=assigned)
    gt, inf = np.asarray(ds.gt[2], np.float64), np.asarray(ds.inferred[2], np.float64)
    shares, base, tex = [], [], []
    for cam in front_rig:
        r_g, r_i = rasterize(gl, gt, ds.faces, cam), rasterize(gl, inf, ds.faces, cam)
        both = (r_g.tri_id >= 0) & (r_i.tri_id >= 0)
        full = assigned[cam.name][0][ds.faces[r_i.tri_id[both]]].all(axis=1)
        shares.append(full.mean())
        e_b, _, _ = direct_sqrt_mse(gl, gt, ds.faces, ds.uv, inf, ds.faces, ds.uv, cam)
        e_t, _, _ = direct_sqrt_mse(gl, gt, ds.faces, ds.uv, inf, ds.faces, ds.uv + disp[cam.name][0], cam)
        base.append(0.6 * np.sqrt(np.mean(e_b[full] ** 2)))
        tex.append(0.6 * np.sqrt(np.mean(e_t[full] ** 2)))
    assert 0.3 < np.mean(shares) < 0.95  # some triangles left out, most kept
    result = evaluate(tiny_dataset, front_rig, tc_path, progress=False)
    assert result.assigned_share.mean == pytest.approx(np.mean(shares), abs=1e-9)
    a = result.material_rmse_assigned_m
    assert a.inferred.mean == pytest.approx(np.mean(base), rel=2e-3)
    assert a.texcoords.mean == pytest.approx(np.mean(tex), rel=2e-3)
    assert result.ratio_material_assigned == pytest.approx(np.mean(base) / np.mean(tex), rel=4e-3)
    js = result.to_json()
    assert js["ratio_material_assigned"] == result.ratio_material_assigned
    assert js["per_camera"]["a"]["assigned_share"]["mean"] == pytest.approx(shares[0], abs=1e-9)
    # Assigned everywhere: the two material errors are one.
    every = save_texcoords(tmp_path / "tc_all", faces=ds.faces, uv=ds.uv, parent=np.stack([np.arange(480)] * 2, 1),
                           source="test", subdiv=0, poses=poses, displacement=disp,
                           assigned={c: np.ones_like(m) for c, m in assigned.items()})
    result = evaluate(tiny_dataset, front_rig, every, progress=False)
    assert result.assigned_share.mean == 1.0
    assert result.material_rmse_assigned_m == result.material_rmse_m
