"""Texture sliding against an independent brute-force float64 ray cast, identity, and
resumable dataset sliding."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import brute_force_first_hit, fail_slide_pose, folded_sheet

from mvtex.data.camera import look_at
from mvtex.data.mesh import apply_parent, subdivide
from mvtex.sliding.dataset import slide_dataset
from mvtex.sliding.options import SlideOptions
from mvtex.sliding.pose import slide_pose
from mvtex.sliding.topology import build_topology

pytestmark = pytest.mark.gl


@pytest.fixture(scope="module")
def oblique():
    return look_at("oblique", (0.7, 0.15, 1.3), (0, 0, 0), width=200, height=200, focal=260.0)


@pytest.mark.slow
@pytest.mark.parametrize("subdiv", [0, 1])
def test_displacements_equal_brute_force_ray_cast(gl, oblique, subdiv):
    faces, uv, gt, inferred = folded_sheet()
    sub = subdivide(faces, len(uv), subdiv)
    d, assigned = slide_pose(gt, inferred, faces, uv, oblique, sub, SlideOptions(subdiv=subdiv, fill="harmonic"))
    X = apply_parent(inferred, sub.parent)
    uv_sub = apply_parent(uv.astype(np.float64), sub.parent)
    idx = np.flatnonzero(assigned)
    assert len(idx) > 0.3 * len(X)
    origin = oblique.center
    dirs = X[idx] - origin
    tri, t, bary = brute_force_first_hit(origin, dirs, gt, faces)
    assert np.all(tri >= 0)
    t_n = np.einsum("kj,kjc->kc", bary, uv[faces[tri]].astype(np.float64))
    err = np.abs(d[idx] - (t_n - uv_sub[idx])).max(axis=1)
    assert np.mean(err <= 1e-5) >= 0.995
    # The assigned vertices are visible: nothing of the inferred mesh hits their ray first.
    sub_faces = sub.faces
    occ_tri, occ_t, _ = brute_force_first_hit(origin, dirs, X, sub_faces)
    assert np.mean(occ_t >= 1 - 1e-3) >= 0.995
    # The folds overhang from this camera: some vertices must be hidden (depth test works).
    tri_all, t_all, _ = brute_force_first_hit(origin, X - origin, X, sub_faces)
    hidden = t_all < 1 - 1e-3
    assert hidden.sum() > 0.02 * len(X) and np.sum(assigned & hidden) <= 0.005 * assigned.sum()
    # Unassigned vertices were filled with finite values.
    assert np.all(np.isfinite(d))


def test_pair_raster_subface_ids_match_raster_of_subdivided_mesh(gl, oblique):
    """The pair raster draws base faces only and reports subdivided face ids from the
    pixel barycentrics: compare with `raster.rasterize` of the subdivided mesh itself."""
    from mvtex.render.raster import rasterize, rasterize_pair

    faces, uv, gt, inferred = folded_sheet(20, 20)
    # The same sheet enlarged about its centre: drawn first, it leaves ids and depths all
    # over the region the next call reads (only that region is cleared).
    centre = gt.mean(axis=0)
    big_gt, big_inferred = centre + 1.6 * (gt - centre), centre + 1.6 * (inferred - centre)
    for levels in (0, 1, 2):
        sub = subdivide(faces, len(uv), levels)
        X = apply_parent(inferred, sub.parent)
        for pixels in (None, np.concatenate([oblique.project(gt)[0], oblique.project(X)[0]])):
            rasterize_pair(gl, big_gt, big_inferred, faces, oblique, levels=levels)
            gt_ids, sub_ids = rasterize_pair(gl, gt, inferred, faces, oblique, levels=levels, pixels=pixels)
            assert np.array_equal(gt_ids, rasterize(gl, gt, faces, oblique, attributes=False).tri_id)
            expected = rasterize(gl, X, sub.faces, oblique, attributes=False).tri_id
            assert np.array_equal(sub_ids >= 0, expected >= 0)
            # Pixel centres exactly on a child edge may go either way: allow a handful.
            assert np.sum(sub_ids != expected) <= max(3, 0.002 * np.sum(expected >= 0))


@pytest.mark.parametrize("angle", [-15.0, 40.0])  # 40: grazing chest silhouettes with the sleeve behind
def test_identity_gives_zero_displacement_and_zero_error(gl, angle):
    from mvtex.evaluation.uv import uv_error_image
    from mvtex.synth.shirt import deform, make_garment, sample_poses

    faces, uv, rest = make_garment()
    pose = sample_poses(3, 1)[1]
    X = deform(rest, uv, pose).astype(np.float64)
    sub = subdivide(faces, len(uv), 0)
    r = np.radians(angle)
    cam = look_at("c", (2.2 * np.sin(r), 0.1, 2.2 * np.cos(r)), (0, 0, 0), width=256, height=256, focal=560.0)
    d, assigned = slide_pose(X, X, faces, uv, cam, sub, SlideOptions(subdiv=0))
    assert assigned.mean() > 0.3
    assert np.abs(d[assigned]).max() <= 1e-6
    _, sqrt_mse = uv_error_image(gl, X, faces, uv, X, faces, uv + d, cam)
    assert sqrt_mse <= 1e-4


def _same_set(a, b):
    from mvtex.data.texcoords import open_texcoords

    ta, tb = open_texcoords(a), open_texcoords(b)
    assert ta.poses == tb.poses and ta.cameras == tb.cameras
    for cam in ta.cameras:
        for p in ta.poses:
            assert np.array_equal(ta.displacement(cam, p), tb.displacement(cam, p))
            assert np.array_equal(ta.assigned(cam, p), tb.assigned(cam, p))


def test_slide_dataset_resumes_after_interruption(gl, tiny_dataset, front_rig, tmp_path, monkeypatch):
    import mvtex.sliding.dataset as jobs
    from mvtex.data.texcoords import open_texcoords

    options = SlideOptions(subdiv=1)
    poses = [0, 2, 3, 5]
    full = slide_dataset(tiny_dataset, front_rig, tmp_path / "full", poses=poses, options=options, progress=False)
    tc = open_texcoords(full, 480)
    assert tc.source == "ts" and tc.subdiv == 1 and tc.poses == poses and tc.cameras == ["a", "b"]
    assert tc.meta["options"] == options.to_json()
    assert not list(full.glob("*/done.npy"))

    monkeypatch.setattr(jobs, "_CHUNK", 2)
    calls = fail_slide_pose(monkeypatch, 6, KeyboardInterrupt("simulated interruption"))
    out = tmp_path / "resumed"
    with pytest.raises(KeyboardInterrupt):
        slide_dataset(tiny_dataset, front_rig, out, poses=poses, options=options, progress=False)
    assert not out.exists() and (tmp_path / "resumed.partial").is_dir()

    calls["n"] = -100  # no more interruptions; count the jobs the rerun does
    slide_dataset(tiny_dataset, front_rig, out, poses=poses, options=options, progress=False)
    assert calls["n"] + 100 == len(poses) * 2 - 4  # two chunks of 2 were done and kept
    assert not (tmp_path / "resumed.partial").exists()
    _same_set(full, out)


def test_slide_dataset_starts_over_with_other_options(gl, tiny_dataset, front_rig, tmp_path, monkeypatch, capsys):
    import mvtex.sliding.dataset as jobs

    poses = [1, 4]
    monkeypatch.setattr(jobs, "_CHUNK", 1)
    original = jobs.slide_pose
    fail_slide_pose(monkeypatch, 2, RuntimeError("boom"))
    with pytest.raises(RuntimeError):
        slide_dataset(tiny_dataset, front_rig, tmp_path / "tc", poses=poses, options=SlideOptions(subdiv=0), progress=False)
    monkeypatch.setattr(jobs, "slide_pose", original)
    out = slide_dataset(tiny_dataset, front_rig, tmp_path / "tc", poses=poses, options=SlideOptions(subdiv=0, fill="fmm"),
                        progress=False)
    assert "starting over" in capsys.readouterr().err
    meta = json.loads((out / "texcoords.json").read_text())
    assert meta["options"]["fill"] == "fmm"
    ref = slide_dataset(tiny_dataset, front_rig, tmp_path / "ref", poses=poses, options=SlideOptions(subdiv=0, fill="fmm"),
                        progress=False)
    _same_set(ref, out)


def test_options_are_checked():
    with pytest.raises(ValueError):
        SlideOptions(fill="nearest")
    with pytest.raises(ValueError):
        SlideOptions(subdiv=-1)
    with pytest.raises(ValueError):
        SlideOptions(break_ratio=0.5)


def open_tube(n_around: int = 48, n_rings: int = 16, radius: float = 0.15, height: float = 0.4):
    """A single-chart open tube (seam vertices split), faces CCW seen from outside."""
    a = np.linspace(0, 2 * np.pi, n_around + 1)
    h = np.linspace(-height / 2, height / 2, n_rings)
    A, Hh = np.meshgrid(a, h)
    positions = np.stack([radius * np.sin(A).ravel(), Hh.ravel(), radius * np.cos(A).ravel()], 1)
    uv = np.stack([A.ravel() / (2 * np.pi), (Hh.ravel() + height / 2) / height], 1).astype(np.float32)
    idx = np.arange(positions.shape[0]).reshape(n_rings, n_around + 1)
    p, q, r, s = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([p, q, r], 1), np.stack([p, r, s], 1)]).astype(np.int32)
    return positions, faces, uv


def test_views_into_an_opening_are_assigned(gl):
    """Looking down into a tube, the far wall is seen from the inside: its hits on the
    (back-facing) inside of gt are the right ones and must be kept; with inferred = gt
    they reproduce T_G."""
    from mvtex.sliding.hits import seen_from_inside

    positions, faces, uv = open_tube()
    camera = look_at("top", (0.0, 0.9, 0.6), (0, 0, 0), width=160, height=160, focal=180.0)
    options = SlideOptions(subdiv=0)
    d, assigned = slide_pose(positions, positions, faces, uv, camera, subdivide(faces, len(uv), 0), options)
    # Independent facing: the outward normal of a tube vertex is its radial direction.
    radial = positions * [1, 0, 1]
    inside = np.einsum("ij,ij->i", radial, positions - camera.center) > 0
    assert np.mean(inside == seen_from_inside(positions, faces, camera.center)) > 0.97
    visible_inside = inside & assigned
    assert visible_inside.sum() > 100
    assert np.abs(d[assigned]).max() < 1e-5


def _hits_both_ways(gl, gt, inferred, faces, uv, reference, camera, options):
    from mvtex.sliding.hits import find_hits_raster

    topo = build_topology(faces, uv, reference, options.subdiv)
    X = topo.positions(inferred)
    faces = np.asarray(faces, np.int64)
    return [find_hits_raster(gl, gt, inferred, faces, X, topo, camera, options, compiled=compiled)
            for compiled in (True, False)]


@pytest.mark.slow
@pytest.mark.parametrize("radius", [0, 1, 2])
def test_compiled_candidate_search_equals_numpy_search(gl, oblique, radius):
    """The compiled kernels (`mvtex.sliding.kernels`) and the NumPy formulation give identical
    hits, bit for bit: on a folded sheet seen whole and cut by the image border (windows
    clipped at the edge), and on the built-in shirt (UV seams: chart tie-breaks; views
    into the collar: hits on the inside; gt = inferred: exact ties)."""
    from mvtex.data.rig import as_rig
    from mvtex.synth.generate import SynthOptions, synthesize

    close = look_at("close", (0.25, 0.1, 0.45), (0, 0, 0), width=160, height=120, focal=260.0)
    faces, uv, gt, inferred = folded_sheet()
    cases = [(gt, inferred, faces, uv, gt, cam) for cam in (oblique, close)]
    shirt = synthesize(SynthOptions(num_poses=3, seed=1))
    rig = as_rig("trapezoid12")
    for cam in (rig.cameras[0], rig.cameras[5], rig.cameras[11]):
        cases.append((shirt["gt"][0].astype(np.float64), shirt["inferred"][0].astype(np.float64), shirt["faces"],
                      shirt["uv"], shirt["rest"].astype(np.float64), cam))
    # gt = inferred: every base vertex's ray passes exactly through a gt vertex, so its
    # incident triangles tie (seams, silhouettes: every tie-break key is used).
    gt1 = shirt["gt"][1].astype(np.float64)
    cases += [(gt1, gt1, shirt["faces"], shirt["uv"], shirt["rest"].astype(np.float64), cam) for cam in rig.cameras[:4]]
    inside = 0
    for gt_, inferred_, faces_, uv_, reference, cam in cases:
        compiled, reference_hits = _hits_both_ways(gl, gt_, inferred_, faces_, uv_, reference, cam,
                                                   SlideOptions(subdiv=1, radius=radius))
        assert compiled.visible.sum() > 50
        for field in ("visible", "tri", "bary", "back", "from_inside"):
            assert np.array_equal(getattr(compiled, field), getattr(reference_hits, field)), (cam.name, field)
        inside += int(np.sum(compiled.back & (compiled.tri >= 0)))
    # Some views reach the inside of the shirt (back-facing hits): that tie-break is exercised.
    assert inside > 0
