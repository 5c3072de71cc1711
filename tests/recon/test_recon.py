"""Multi-view reconstruction: UV lookup against brute force, triangulation against OpenCV,
pycolmap and scipy, exact recovery when inferred = gt, hypothesis disambiguation, and the
exported PLY / COLMAP model read back by trimesh, pycolmap and the colmap binary."""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pytest
import trimesh
from helpers import grid_mesh, sheet_in_front, three_camera_rig, wave

from mvtex.data.camera import look_at
from mvtex.data.mesh import barycentric_2d, subdivide
from mvtex.util.errors import InputError

# -- UV lookup ----------------------------------------------------------------------------

def test_locate_uv_matches_brute_force(gl):
    """Every (point, containing triangle) pair, also where jittered texcoords fold over."""
    from mvtex.recon.locate import locate_uv

    rng = np.random.default_rng(3)
    faces, uv, _ = grid_mesh(20, 18)
    texcoords = uv + rng.normal(scale=0.02, size=uv.shape)  # ~ 0.4 cell: fold-overs, 3 layers deep
    points = rng.uniform(0.02, 0.98, size=(1000, 2))
    pi, fi, bary = locate_uv(points, faces, texcoords, resolution=256)
    # Brute force: every point against every triangle.
    P = np.repeat(np.arange(len(points)), len(faces))
    F = np.tile(np.arange(len(faces)), len(points))
    b = barycentric_2d(points[P], texcoords[faces[F]])
    inside = np.all(b >= -1e-7, axis=1)
    expected = set(zip(P[inside].tolist(), F[inside].tolist()))
    assert set(zip(pi.tolist(), fi.tolist())) == expected
    assert sum(np.bincount(P[inside]) > 2) >= 5  # the test does exercise several hypotheses
    # Barycentrics reproduce the points.
    recon = np.einsum("hk,hkj->hj", bary, texcoords[faces[fi]])
    assert np.abs(recon - points[pi]).max() < 1e-12


# -- triangulation -----------------------------------------------------------------------------

def test_taubin_keeps_constants_and_damps_noise():
    from mvtex.data.mesh import adjacency
    from mvtex.recon.triangulate import taubin_smooth

    faces, uv, _ = grid_mesh(30, 30)
    adj = adjacency(faces, len(uv))
    const = np.tile([0.01, -0.02, 0.003], (len(uv), 1))
    assert np.abs(taubin_smooth(const, adj, 10) - const).max() < 1e-15
    noise = np.random.default_rng(0).normal(size=(len(uv), 3))
    assert taubin_smooth(noise, adj, 10).std() < 0.5 * noise.std()
    # A field one grid wide passes nearly unchanged (Taubin's low-pass does not shrink).
    smooth = np.sin(np.pi * uv[:, :1]) * np.sin(np.pi * uv[:, 1:]) * np.ones((1, 3))
    assert np.abs(taubin_smooth(smooth, adj, 10) - smooth).max() < 0.05


# -- reconstruct ------------------------------------------------------------------------------

def test_identity_reproduces_gt(gl):
    """inferred = gt, T_N = T_G: triangulated vertices are the gt vertices."""
    from mvtex.recon.triangulate import reconstruct

    faces, uv, rest = grid_mesh(30, 26)
    gt = wave(rest, 0.015, 0.4)
    rig = three_camera_rig()
    rec = reconstruct(uv, gt, faces, uv, {c.name: uv for c in rig}, rig)
    tri = rec.triangulated
    assert tri.mean() > 0.8
    assert np.abs(rec.points[tri] - gt[tri]).max() < 1e-6
    assert np.nanmax(rec.reprojection_error) < 1e-6
    # Observations are the gt vertices' projections.
    for cam in rig:
        o = rec.observations[cam.name]
        seen = np.isfinite(o[:, 0])
        assert seen.sum() > 0.8 * len(uv)
        assert np.abs(o[seen] - cam.project(gt[seen])[0]).max() < 1e-6


def test_identity_on_subdivided_mesh(gl):
    """Same on a subdivided texcoord mesh: the gt vertex lies on its midpoint triangles."""
    from mvtex.data.mesh import apply_parent
    from mvtex.recon.triangulate import reconstruct

    faces, uv, rest = grid_mesh(24, 20)
    gt = wave(rest, 0.015, 1.1)
    sub = subdivide(faces, len(uv), 1)
    uv_sub = apply_parent(uv.astype(np.float64), sub.parent)
    rig = three_camera_rig()
    rec = reconstruct(uv, apply_parent(gt, sub.parent), sub.faces, uv_sub, {c.name: uv_sub for c in rig}, rig,
                      gt_faces=faces)
    tri = rec.triangulated
    assert tri.mean() > 0.8
    assert np.abs(rec.points[tri] - gt[tri]).max() < 1e-6


def test_fold_over_hypotheses_are_disambiguated(gl):
    """Camera b's texcoords fold over (one vertex dragged across its neighbours): several
    triangles contain some T_G. With two cameras no observation can be voted out, so only
    the choice of the hypotheses whose rays agree gives back the gt points. The triangle
    test (on by default) drops the dragged fans' hypotheses before they compete: the same
    points."""
    from mvtex.recon.locate import locate_uv
    from mvtex.recon.triangulate import ReconOptions, reconstruct

    faces, uv, rest = grid_mesh(30, 26)
    gt = wave(rest, 0.015, 0.4)
    rig = three_camera_rig().select(["a", "b"])
    bad = uv.astype(np.float64).copy()
    for k in (13 * 30 + 12, 7 * 30 + 8):
        bad[k] = uv[k + 6]  # its fan now overlaps the cells six columns to the right
    pi, fi, bary = locate_uv(uv, faces, bad)
    points = np.einsum("hk,hkj->hj", bary, gt[faces[fi]])
    wrong = np.unique(pi[np.linalg.norm(points - gt[pi], axis=1) > 1e-3])  # has a false hypothesis
    rec = reconstruct(uv, gt, faces, uv, {"a": uv, "b": bad}, rig, ReconOptions(max_stretch=None))
    assert rec.stats["ambiguous_vertices"] > 0 and rec.rejected_observations["alternative"] > 0
    assert rec.triangulated[wrong].sum() >= 8
    tri = rec.triangulated
    assert np.abs(rec.points[tri] - gt[tri]).max() < 1e-6
    screened = reconstruct(uv, gt, faces, uv, {"a": uv, "b": bad}, rig)
    assert screened.rejected_observations["stretched_triangle"] > 0
    assert screened.triangulated[wrong].sum() >= 8
    tri = screened.triangulated
    assert np.abs(screened.points[tri] - gt[tri]).max() < 1e-6


def test_visibility_against_an_occluder_matches_ray_casting(gl):
    """A square card 0.3 m in front of the flat sheet hides part of it from a camera: the
    points `visible_points` drops are those whose ray to the camera crosses the card
    (closed form), up to the one-pixel band along the card's outline."""
    from mvtex.recon.locate import visible_points
    from mvtex.render.raster import rasterize

    faces, uv, rest = grid_mesh(60, 50)
    cam = three_camera_rig()["b"]
    card = np.array([[-0.1, -0.05, 0.3], [0.08, -0.05, 0.3], [0.08, 0.1, 0.3], [-0.1, 0.1, 0.3]])
    card_faces = np.array([[0, 1, 2], [0, 2, 3]])
    rng = np.random.default_rng(2)
    f = rng.integers(0, len(faces), 3000)
    b = rng.dirichlet(np.ones(3), 3000)
    points = np.einsum("hk,hkj->hj", b, rest[faces[f]])
    cloth = rasterize(gl, rest, faces, cam)
    occluder = rasterize(gl, card, card_faces, cam)
    alone, _ = visible_points(cam, points, f, cloth)
    seen, pixels = visible_points(cam, points, f, cloth, [occluder])
    assert alone.all()
    # Closed form: where the segment point -> camera centre crosses z = 0.3.
    C = cam.center
    s = (0.3 - points[:, 2]) / (C[2] - points[:, 2])
    hit = points + s[:, None] * (C - points)
    behind = (hit[:, 0] > -0.1) & (hit[:, 0] < 0.08) & (hit[:, 1] > -0.05) & (hit[:, 1] < 0.1)
    outline, _ = cam.project(card)
    lo, hi = outline.min(axis=0), outline.max(axis=0)
    inner = np.all((pixels > lo + 1.5) & (pixels < hi - 1.5), axis=1)
    outer = np.any((pixels < lo - 1.5) | (pixels > hi + 1.5), axis=1)
    assert behind.sum() > 300
    assert not seen[behind & inner].any()
    assert seen[~behind & outer].all()


def test_untriangulated_get_the_extended_displacement(gl):
    """Flat gt, inferred 1 cm in front of it. T_N by exact ray casting (closed form: the
    ray through an inferred vertex meets the plane z = 0). Triangulation recovers gt; the
    vertices seen by < 2 cameras get X_N + the harmonic extension of the constant
    displacement, i.e. gt as well."""
    from mvtex.recon.triangulate import reconstruct

    faces, uv, rest, inferred, rig, T = sheet_in_front()
    rec = reconstruct(uv, inferred, faces, uv, T, rig)
    assert 0.3 < rec.triangulated.mean() < 0.97
    assert np.abs(rec.points - rest).max() < 1e-6


def test_fill_on_the_rest_shape_extends_a_linear_field_exactly():
    """Harmonic (cotangent) extension reproduces fields linear in the shape it is solved on
    (closed form on a flat sheet): solved on the flat rest shape, a displacement linear in
    the rest coordinates known on the border and a few rows comes back exactly inside;
    solved on the wavy inferred shape it does not."""
    from mvtex.recon.triangulate import ReconOptions, pool_and_fill

    faces, uv, rest = grid_mesh(30, 26)
    inferred = wave(rest, 0.03, 0.7, wavelength=0.2)
    disp = rest @ np.array([[0.02, 0.0, -0.01], [0.01, 0.03, 0.0], [0.0, 0.0, 0.0]]) + np.array([0.001, 0.0, 0.002])
    rows, cols = np.divmod(np.arange(len(uv)), 30)
    known = (rows == 0) | (rows == 25) | (cols == 0) | (cols == 29) | (rows % 8 == 4)
    points = np.where(known[:, None], inferred + disp, np.nan)
    on_rest, _, _ = pool_and_fill(points, known, inferred, faces, ReconOptions(fill_shape="rest"), rest=rest)
    on_inferred, _, _ = pool_and_fill(points, known, inferred, faces, ReconOptions(fill_shape="inferred"), rest=rest)
    assert np.abs(on_rest - (inferred + disp)).max() < 1e-12
    assert np.abs(on_inferred - (inferred + disp)).max() > 1e-5
    assert np.array_equal(on_rest[known], on_inferred[known])
    without_rest, _, _ = pool_and_fill(points, known, inferred, faces, ReconOptions(fill_shape="rest"))
    assert np.array_equal(without_rest, on_inferred)  # no rest shape: the inferred one


def test_engines_agree_on_a_noisy_reconstruction(gl):
    """Noisy texcoords, three cameras: `engine="pycolmap"` triangulates the same vertices
    to the same points as the default engine (< 1e-6 m), through every step."""
    from mvtex.recon.triangulate import ReconOptions, reconstruct

    faces, uv, rest = grid_mesh(24, 20)
    gt = wave(rest, 0.015, 0.4)
    rig = three_camera_rig()
    rng = np.random.default_rng(5)
    T = {c.name: uv + rng.normal(scale=1e-3, size=uv.shape) for c in rig}
    T["c"][rng.choice(len(uv), 40, replace=False)] += 0.03  # ~3.5 px outliers
    for k in (13 * 24 + 12, 7 * 24 + 8):
        T["b"][k] = uv[k + 5]  # fold-overs: ambiguous hypotheses
    # A loose vote and no triangle test: the engine's outlier loop and rejection run too.
    runs = {engine: reconstruct(uv, gt, faces, uv, T, rig, ReconOptions(max_reprojection_px=1.0, consensus_px=4.0,
                                                                        max_stretch=None, engine=engine))
            for engine in ("mvtex", "pycolmap")}
    ours, colmap = runs["mvtex"], runs["pycolmap"]
    # Every step ran: ambiguity, the vote, outlier removal, rejection.
    assert ours.triangulated.sum() > 400 and ours.stats["ambiguous_vertices"] > 0
    assert ours.rejected_observations["disagreement"] > 0
    assert ours.rejected_observations["reprojection"] > 20 and ours.rejected["reprojection"] > 0
    assert ours.stats == colmap.stats
    assert np.array_equal(ours.triangulated, colmap.triangulated)
    assert np.abs(ours.points - colmap.points).max() < 1e-6
    assert ours.rejected == colmap.rejected
    assert ours.rejected_observations == colmap.rejected_observations


def test_reconstruct_input_errors():
    from mvtex.recon.triangulate import ReconOptions, reconstruct

    faces, uv, rest = grid_mesh(6, 5)
    rig = three_camera_rig()
    with pytest.raises(ValueError, match=r"inferred_positions must have shape \(n',3\), got \(30, 2\)"):
        reconstruct(uv, rest[:, :2], faces, uv, {c.name: uv for c in rig}, rig)
    with pytest.raises(ValueError, match=r"texcoords\['a'\] must have shape \(30,2\), got \(29, 2\)"):
        reconstruct(uv, rest, faces, uv, {c.name: uv[:-1] for c in rig}, rig)
    with pytest.raises(ValueError, match="≥ 2 rig cameras"):
        reconstruct(uv, rest, faces, uv, {"a": uv}, rig)
    with pytest.raises(ValueError, match="engine must be one of mvtex, pycolmap, got 'ceres'"):
        ReconOptions(engine="ceres")
    with pytest.raises(ValueError, match=r"max_stretch must be a finite number > 1 or None, got 1.0"):
        ReconOptions(max_stretch=1.0)
    with pytest.raises(ValueError, match=r"consensus_px must be a finite number > 0 \(px\), got nan"):
        ReconOptions(consensus_px=float("nan"))
    with pytest.raises(ValueError, match="consensus_scale must be a finite number ≥ 0 or None, got -1"):
        ReconOptions(consensus_scale=-1)
    with pytest.raises(ValueError, match="fill_shape must be one of rest, inferred, got 'gt'"):
        ReconOptions(fill_shape="gt")
    with pytest.raises(ValueError, match=r"max_combinations must be an integer in \[1, 100000\], got 0"):
        ReconOptions(max_combinations=0)


# -- the command: files ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def identity_run(gl, tmp_path_factory, tiny_dataset):
    """An identity texcoord set (inferred replaced by gt, d = 0) and its triangulation."""
    from mvtex.data.dataset import load_dataset, save_dataset
    from mvtex.data.texcoords import open_texcoords, save_texcoords
    from mvtex.recon.pose import triangulate_pose

    base = load_dataset(tiny_dataset)
    root = tmp_path_factory.mktemp("recon")
    save_dataset(root / "ds", faces=base.faces, uv=base.uv, gt=base.gt, inferred=base.gt, poses=base.poses,
                 rest=base.rest)
    ds = load_dataset(root / "ds")
    rig = three_camera_rig()
    n = ds.num_vertices
    poses = [1, 4]
    save_texcoords(root / "tc", faces=ds.faces, uv=ds.uv, parent=np.stack([np.arange(n)] * 2, 1), source="identity",
                   subdiv=0, poses=poses, displacement={c: np.zeros((2, n, 2)) for c in rig.names},
                   assigned={c: np.ones((2, n), bool) for c in rig.names})
    tc = open_texcoords(root / "tc", n)
    report = triangulate_pose(ds, rig, tc, 4, root / "out", progress=False)
    # The report's JSON is report.json, key for key.
    assert json.loads((root / "out" / "report.json").read_text()) == json.loads(json.dumps(report.to_json()))
    assert report.rmse_triangulated_m.ratio == report.rmse_triangulated_m.inferred / report.rmse_triangulated_m.reconstructed
    return ds, rig, tc, report.to_json(), root / "out"


@pytest.mark.slow
def test_slide_with_inferred_equal_gt_reproduces_gt(identity_run):
    """Texture sliding with inferred = gt assigns T_N = T_G (exact ray casting onto itself);
    triangulating that texcoord set gives back gt, with and without subdivision."""
    from mvtex.data.texcoords import open_texcoords
    from mvtex.recon.pose import triangulate_pose
    from mvtex.sliding.dataset import slide_dataset
    from mvtex.sliding.options import SlideOptions

    ds, rig, tc, report, out = identity_run
    for subdiv in (0, 1):
        path = out.parent / f"slid{subdiv}"
        slide_dataset(ds, rig, path, poses=[2], options=SlideOptions(subdiv=subdiv), progress=False)
        result = triangulate_pose(ds, rig, open_texcoords(path, ds.num_vertices), 2, None, progress=False).to_json()
        assert result["num_triangulated"] > 0.7 * ds.num_vertices
        assert result["rmse_triangulated_m"]["reconstructed"] <= 1e-6
        assert result["mean_reprojection_error_px"] < 1e-3


def test_triangulate_pose_identity_report(identity_run):
    ds, rig, tc, report, out = identity_run
    assert report["pose"] == 4 and report["num_vertices"] == ds.num_vertices
    assert report["num_triangulated"] > 0.8 * ds.num_vertices
    assert report["rmse_triangulated_m"]["reconstructed"] <= 1e-6
    assert report["rmse_m"]["inferred"] == pytest.approx(0.0, abs=1e-9)
    assert report["mean_reprojection_error_px"] < 1e-5
    assert sum(report["rejected"].values()) == ds.num_vertices - report["num_triangulated"]
    import json

    assert json.loads((out / "report.json").read_text()) == json.loads(json.dumps(report))
    for name in rig.names:
        assert (out / "images" / f"{name}.png").is_file()
    assert (out / "comparison.png").is_file()


def test_ply_loads_with_trimesh(identity_run):
    import trimesh

    ds, rig, tc, report, out = identity_run
    mesh = trimesh.load(out / "reconstruction.ply", process=False)
    assert len(mesh.vertices) == ds.num_vertices
    assert np.array_equal(mesh.faces, ds.faces)
    assert np.abs(mesh.visual.uv - ds.uv).max() < 1e-7
    raw = mesh.metadata["_ply_raw"]["vertex"]["data"]
    assert int(raw["triangulated"].sum()) == report["num_triangulated"]
    tri = raw["triangulated"].astype(bool)
    assert np.abs(mesh.vertices[tri] - ds.gt[4][tri]).max() < 1e-6


def test_colmap_model_reads_back(identity_run):
    import pycolmap

    from mvtex.formats.colmap import model_summary

    ds, rig, tc, report, out = identity_run
    rec = pycolmap.Reconstruction(str(out / "colmap"))
    assert rec.num_images() == len(rig) and rec.num_points3D() == report["num_triangulated"]
    assert {rec.images[i].name for i in rec.images} == {f"{c}.png" for c in rig.names}
    summary = model_summary(out / "colmap")
    assert summary["mean_reprojection_error_px"] == pytest.approx(report["mean_reprojection_error_px"], abs=1e-6)
    # COLMAP projects the points onto their observations (+0.5 convention on both sides).
    for pid, point in list(rec.points3D.items())[:50]:
        for el in point.track.elements:
            image = rec.images[el.image_id]
            uv = image.project_point(point.xyz)
            assert np.linalg.norm(uv - image.points2D[el.point2D_idx].xy) < 1e-5


def test_colmap_model_reprojection_equals_ours_with_noise(gl, tmp_path):
    """Noisy texcoords: COLMAP's reprojection error of the exported model equals ours."""
    from mvtex.formats.colmap import model_summary
    from mvtex.recon.export import export_reconstruction
    from mvtex.recon.triangulate import ReconOptions, reconstruct

    faces, uv, rest = grid_mesh(24, 20)
    gt = wave(rest, 0.015, 0.4)
    rig = three_camera_rig()
    rng = np.random.default_rng(5)
    T = {c.name: uv + rng.normal(scale=1e-3, size=uv.shape) for c in rig}
    rec = reconstruct(uv, gt, faces, uv, T, rig, ReconOptions(max_reprojection_px=5.0))
    assert rec.triangulated.sum() > 100
    ours = float(np.mean(rec.reprojection_error[rec.triangulated]))
    assert ours > 0.05
    export_reconstruction(tmp_path / "out", rec, rig, faces=faces, uv=uv, gt=None, rest=None, inferred_mesh=None,
                          report={"pose": 0})
    assert model_summary(tmp_path / "out" / "colmap")["mean_reprojection_error_px"] == pytest.approx(ours, rel=1e-6)


@pytest.mark.skipif(shutil.which("colmap") is None, reason="colmap binary not installed")
def test_colmap_binary_reads_model(identity_run):
    ds, rig, tc, report, out = identity_run
    run = subprocess.run(["colmap", "model_analyzer", "--path", str(out / "colmap")], capture_output=True, text=True,
                         timeout=120, env={"QT_QPA_PLATFORM": "offscreen", "PATH": "/usr/bin:/bin"})
    assert run.returncode == 0, run.stderr
    text = run.stdout + run.stderr
    assert f"Points: {report['num_triangulated']}" in text
    assert f"Images: {len(rig)}" in text


def test_bad_inputs(identity_run):
    from mvtex.recon.pose import triangulate_pose

    ds, rig, tc, report, out = identity_run
    with pytest.raises(InputError, match="texcoords.json: pose 0"):
        triangulate_pose(ds, rig, tc, 0, None, progress=False)
    with pytest.raises(InputError, match="2 cameras"):
        triangulate_pose(ds, rig.select(["a"]), tc, 4, None, progress=False)


@pytest.mark.slow
def test_triangulate_smooth_through_the_command_line(identity_run, tmp_path, capsys):
    """`mvtex triangulate --smooth --json` on noisy texcoords prints one JSON object: the
    unsmoothed numbers equal a plain run's, and smoothing lowers the strain of the noisy
    reconstruction toward gt's."""
    import json

    from mvtex.cli import main
    from mvtex.data.rig import save_rig
    from mvtex.data.texcoords import save_texcoords

    ds, rig, tc, report, out = identity_run
    n = ds.num_vertices
    rng = np.random.default_rng(11)
    save_texcoords(tmp_path / "noisy", faces=ds.faces, uv=ds.uv, parent=np.stack([np.arange(n)] * 2, 1),
                   source="identity+noise", subdiv=0, poses=[4],
                   displacement={c: rng.normal(scale=4e-4, size=(1, n, 2)) for c in rig.names},
                   assigned={c: np.ones((1, n), bool) for c in rig.names})
    save_rig(rig, tmp_path / "rig.yaml")
    runs = {}
    for flags in ((), ("--smooth",)):
        argv = [str(ds.path), "--rig", str(tmp_path / "rig.yaml"), "--texcoords", str(tmp_path / "noisy"),
                "--pose", "4", "--out", str(tmp_path / f"out{len(flags)}"), "--max-reprojection-px", "5",
                "--json", "--quiet", *flags]
        assert main(["triangulate", *argv]) == 0
        stdout = capsys.readouterr().out
        runs[flags] = json.loads(stdout)  # exactly one JSON object: json.loads rejects trailing text
    plain, smooth = runs[()], runs[("--smooth",)]
    assert plain["smooth"] == {"enabled": False} and plain["options"]["smooth"] is False
    assert smooth["options"]["smooth"] is True and smooth["smooth"]["enabled"] is True
    assert smooth["smooth"]["iterations"] == smooth["options"]["smooth_iterations"] == 10
    assert smooth["num_triangulated"] == plain["num_triangulated"] > 0.5 * n
    assert smooth["smooth"]["before"]["rmse_m"] == pytest.approx(plain["rmse_m"]["reconstructed"], rel=1e-12)
    before = smooth["smooth"]["before"]["strain_energy"]["mean_abs_strain"]
    after = smooth["strain_energy"]["reconstructed"]["mean_abs_strain"]
    assert before == pytest.approx(plain["strain_energy"]["reconstructed"]["mean_abs_strain"], rel=1e-12)
    gt_strain = smooth["strain_energy"]["gt"]["mean_abs_strain"]
    assert abs(after - gt_strain) < 0.2 * abs(before - gt_strain)
    assert smooth["rmse_m"]["reconstructed"] < plain["rmse_m"]["reconstructed"]
    on_disk = json.loads((tmp_path / "out1" / "report.json").read_text())
    assert on_disk == smooth


def test_no_observation_the_body_hides(gl):
    """A box between a wavy sheet and three cameras (inferred = gt, T_N = T_G, so every
    located point is the gt vertex): every observation the reconstruction uses is of a
    vertex whose ray to that camera misses the box (trimesh's exact ray cast), and without
    the body some would not be."""
    import trimesh

    from mvtex.recon.triangulate import reconstruct

    embree = pytest.importorskip("trimesh.ray.ray_pyembree")
    faces, uv, rest = grid_mesh(40, 34)
    gt = wave(rest, 0.015, 0.4)
    rig = three_camera_rig()
    box = trimesh.creation.box(extents=(0.12, 0.08, 0.1), transform=trimesh.transformations.translation_matrix(
        (0.02, 0.01, 0.45)))
    body = (np.asarray(box.vertices, np.float64), np.asarray(box.faces, np.int64))
    texcoords = {c.name: uv for c in rig}
    worn = reconstruct(uv, gt, faces, uv, texcoords, rig, body=body)
    bare = reconstruct(uv, gt, faces, uv, texcoords, rig)
    caster = embree.RayMeshIntersector(box)

    def hidden_by_box(cam, vertices):
        origins = np.repeat(cam.center[None], len(vertices), axis=0)
        to = gt[vertices] - origins
        dist = np.linalg.norm(to, axis=1)
        hit = caster.intersects_first(origins, to / dist[:, None])
        hidden = np.zeros(len(vertices), bool)
        met = hit >= 0
        if met.any():
            loc, ray, _ = caster.intersects_location(origins[met], (to / dist[:, None])[met], multiple_hits=False)
            first = np.full(int(met.sum()), np.inf)
            first[ray] = np.linalg.norm(loc - origins[met][ray], axis=1)
            hidden[np.flatnonzero(met)] = first < dist[met]
        return hidden

    through = 0
    for cam in rig:
        used = np.flatnonzero(np.isfinite(worn.observations[cam.name][:, 0]))
        assert len(used) > 0.4 * len(uv)
        assert not hidden_by_box(cam, used).any(), cam.name
        through += int(hidden_by_box(cam, np.flatnonzero(np.isfinite(bare.observations[cam.name][:, 0]))).sum())
    assert through > 100
    assert worn.rejected_observations["hidden_by_body"] > 100
    assert bare.rejected_observations["hidden_by_body"] == 0
    # Where it still triangulates, the body changes nothing: the same exact points.
    both = worn.triangulated & bare.triangulated
    assert both.sum() > 0.4 * len(uv)
    assert np.abs(worn.points[both] - gt[both]).max() < 1e-6


# -- trust: a predictor's uncertainty, or the cameras' agreement ------------------------------

def _rmse(a, b):
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


def test_a_bad_predictor_with_its_uncertainty_falls_back_to_the_inferred_mesh(gl):
    """Texcoords of a deliberately bad model (a smooth field 2-3 px wide, different per
    camera, added to the exact T_N) that reports its uncertainty: the reconstruction keeps
    the inferred mesh (all-vertex RMSE against gt within 3 % of the inferred mesh's, both
    computed here from gt), where taking every point makes it far worse. The same
    uncertainty machinery, given the exact T_N and a small uncertainty, still recovers gt."""
    from mvtex.recon.triangulate import ReconOptions, reconstruct

    faces, uv, rest, inferred, rig, exact = sheet_in_front()
    rng = np.random.default_rng(11)
    bad, std = {}, {}
    for name, T in exact.items():
        k = rng.normal(size=(2, 2)) * 12
        phase = rng.uniform(0, 2 * np.pi, 2)
        field = np.stack([np.sin(uv @ k[0] + phase[0]), np.cos(uv @ k[1] + phase[1])], axis=1)
        bad[name] = T + 0.02 * field
        std[name] = np.full(len(uv), 0.02 * np.sqrt(2 / 2), np.float32)  # its RMS error length: 0.02
    options = ReconOptions(shrink=0.7, consensus_scale=4)
    inferred_rmse = _rmse(inferred, rest)
    taken = reconstruct(uv, inferred, faces, uv, bad, rig, ReconOptions(shrink=0, consensus_scale=4))
    trusted = reconstruct(uv, inferred, faces, uv, bad, rig, options, uncertainty=std)
    assert taken.triangulated.mean() > 0.2  # the cameras do agree on points: the vote alone keeps them
    assert _rmse(taken.points, rest) > 1.5 * inferred_rmse
    assert trusted.sigma is not None and np.nanmedian(trusted.sigma) > 0.005
    assert abs(_rmse(trusted.points, rest) / inferred_rmse - 1) < 0.03
    good = reconstruct(uv, inferred, faces, uv, exact, rig, options,
                       uncertainty={c: np.full(len(uv), 1e-5, np.float32) for c in exact})
    assert _rmse(good.points, rest) < 0.02 * inferred_rmse


def test_without_uncertainty_the_cameras_disagreement_decides(gl):
    """No uncertainty: each observation's spread is the pose's disagreement between the
    cameras (`consistency_sigma_px`, against its definition computed here: squared
    reprojection errors over 2 per observation less 3 per point). Texcoords with
    independent noise of several pixels per camera leave the inferred mesh (within 5 %),
    exact ones are reconstructed."""
    from mvtex.recon.geometry import reprojection_errors
    from mvtex.recon.triangulate import ReconOptions, consistency_sigma_px, reconstruct

    faces, uv, rest, inferred, rig, exact = sheet_in_front()
    rng = np.random.default_rng(12)
    noisy = {name: T + rng.normal(scale=0.012, size=T.shape) for name, T in exact.items()}
    options = ReconOptions(shrink=0.7, consensus_scale=4)
    inferred_rmse = _rmse(inferred, rest)
    taken = reconstruct(uv, inferred, faces, uv, noisy, rig, ReconOptions(shrink=0, consensus_scale=4))
    trusted = reconstruct(uv, inferred, faces, uv, noisy, rig, options)
    assert taken.triangulated.sum() > 50 and _rmse(taken.points, rest) > 1.2 * inferred_rmse
    assert abs(_rmse(trusted.points, rest) / inferred_rmse - 1) < 0.05
    exact_rec = reconstruct(uv, inferred, faces, uv, exact, rig, options)
    assert _rmse(exact_rec.points, rest) < 0.02 * inferred_rmse

    cams = list(rig)
    X = rng.normal(scale=0.05, size=(40, 3))
    pixels = np.stack([c.project(X)[0] for c in cams], axis=1) + rng.normal(scale=0.3, size=(40, 3, 2))
    weights = np.ones((40, 3))
    weights[:10, 2] = 0
    err = reprojection_errors(cams, X, pixels)
    expected = np.sqrt(np.sum(np.where(weights > 0, err, 0) ** 2) / (2 * weights.sum() - 3 * 40))
    assert consistency_sigma_px(cams, X, pixels, weights) == pytest.approx(expected, rel=1e-12)


def test_a_body_no_pixel_centre_sees_still_hides_observations(gl):
    """A thin box (0.5 mm wide) between the flat sheet and a camera, projecting between two
    pixel columns (no raster shows it): the observations of the column of vertices whose
    rays it crosses are hidden by the body, every other vertex is observed (closed form,
    the slab method; T_N = T_G so each vertex is located at itself)."""
    from mvtex.recon.locate import collect_hypotheses
    from mvtex.render.raster import rasterize

    faces, uv, rest = grid_mesh(31, 31)
    cam = look_at("front", (0.0, 0.0, 2.0), (0, 0, 0), width=160, height=160, focal=400.0)
    lo, hi = np.array([0.05 - 2.5e-4, -0.2, 0.99]), np.array([0.05 + 2.5e-4, 0.2, 1.0])
    box = trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((lo + hi) / 2))
    body = (np.asarray(box.vertices, np.float64), np.asarray(box.faces, np.int64))
    assert not rasterize(gl, rest, faces, cam, occluder=body).body.any()
    hyp, counts = collect_hypotheses(uv, rest, faces, {"front": uv}, [cam], body=body, ctx=gl)
    d = rest - cam.center
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (lo - cam.center) / d, (hi - cam.center) / d
    near, far = np.nanmax(np.minimum(t0, t1), axis=1), np.nanmin(np.maximum(t0, t1), axis=1)
    hidden = (near <= far) & (far > 0) & (near < 1)
    assert hidden.sum() >= 31
    observed = np.zeros(len(rest), bool)
    observed[hyp.vertex] = True
    assert np.array_equal(observed, ~hidden)
    assert counts["hidden_by_body"] >= hidden.sum()
