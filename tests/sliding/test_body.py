"""The body in texture sliding (DESIGN §5 "The body"): a box in front of a flat sheet in
closed form, and a folded sheet with a body cut into it against a brute-force float64 ray
cast, the NumPy formulation and the Embree path."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from helpers import brute_force_first_hit, folded_sheet, grid_mesh

from mvtex.data.camera import look_at
from mvtex.data.mesh import apply_parent, subdivide
from mvtex.sliding.hits import find_hits_raster
from mvtex.sliding.options import SlideOptions
from mvtex.sliding.pose import slide_pose
from mvtex.sliding.topology import body_topology, build_topology

pytestmark = pytest.mark.gl

CENTRE = np.array([0.0, 0.0, 2.0])  # the camera, looking down -z at the sheet in z = 0
BOX = (np.array([-0.1, -0.08, 0.8]), np.array([0.05, 0.12, 1.0]))  # between them


def box_mesh(lo, hi):
    """A closed box (trimesh's, faces outward): positions (8,3) float64, faces (12,3)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    box = trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((lo + hi) / 2))
    return np.asarray(box.vertices, np.float64), np.asarray(box.faces, np.int64)


def segment_meets_box(origin, points, lo, hi):
    """(k,) bool: the open segment origin -> points[k] passes through the box [lo, hi]
    (the slab method, in closed form)."""
    d = points - origin
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (lo - origin) / d
        t1 = (hi - origin) / d
    near = np.nanmax(np.minimum(t0, t1), axis=1)
    far = np.nanmin(np.maximum(t0, t1), axis=1)
    return (near <= far) & (far > 0) & (near < 1)


def _clear_cases(origin, points, margin=0.004):
    """Hidden and open vertices by the closed form, leaving out those within `margin` (m) of
    the box's silhouette (pixel sampling decides those either way)."""
    lo, hi = BOX
    hidden = segment_meets_box(origin, points, lo + margin, hi - margin)
    grown = segment_meets_box(origin, points, lo - margin, hi + margin)
    return hidden, ~grown


@pytest.fixture(scope="module")
def front():
    return look_at("front", CENTRE, (0, 0, 0), width=160, height=160, focal=400.0)


@pytest.mark.parametrize("subdiv", [0, 1])
@pytest.mark.parametrize("case", ["hides the vertex", "hides the gt cloth"])
def test_box_in_front_of_a_flat_sheet(gl, front, case, subdiv):
    """gt is the flat sheet; the inferred sheet is gt itself (the box hides the inferred
    vertex: rule 2) or gt scaled towards the camera, in front of the box, on the same rays
    (the box hides the gt cloth behind it: rule 3). Either way the vertices whose ray the
    box cuts are unassigned, and every other one is assigned with d = 0."""
    faces, uv, gt = grid_mesh(31, 31)
    inferred = gt if case == "hides the vertex" else CENTRE + 0.3 * (gt - CENTRE)
    body = box_mesh(*BOX)
    options = SlideOptions(subdiv=subdiv)
    sub = subdivide(faces, len(uv), subdiv)
    d, assigned = slide_pose(gt, inferred, faces, uv, front, sub, options, body=body)
    hidden, open_ = _clear_cases(CENTRE, apply_parent(gt, sub.parent))
    assert hidden.sum() > 40 and open_.sum() > 400
    assert not assigned[hidden].any()
    assert assigned[open_].all()
    assert np.abs(d[open_]).max() < 1e-6
    # Which rule did it: the hit search tells a hidden vertex from a hidden gt hit.
    topo = build_topology(faces, uv, gt, subdiv)
    hits = find_hits_raster(gl, gt, inferred, faces.astype(np.int64), topo.positions(inferred), topo, front,
                            options, body=(body[0], body_topology(body[1], topo)))
    if case == "hides the vertex":
        assert not hits.visible[hidden].any()
    else:
        assert hits.visible[hidden].all() and (hits.tri[hidden] == -1).all()


def test_without_a_body_the_box_is_not_there(gl, front):
    """The same sheet with no body: every vertex the camera sees is assigned."""
    faces, uv, gt = grid_mesh(31, 31)
    d, assigned = slide_pose(gt, gt, faces, uv, front, subdivide(faces, len(uv), 0), SlideOptions(subdiv=0))
    hidden, _ = _clear_cases(CENTRE, gt)
    assert assigned[hidden].all()


def worn_folded_sheet():
    """The folded sheet with a body: a cylinder between it and the oblique camera (an arm),
    a sphere that both cloth meshes cut into, and a slab behind the sheet (the torso)."""
    faces, uv, gt, inferred = folded_sheet()
    arm = trimesh.creation.cylinder(radius=0.04, height=0.7, sections=24,
                                    transform=trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
    arm.apply_translation((0.3, 0.0, 0.55))
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.06)
    ball.apply_translation((-0.1, -0.2, -0.02))
    torso = trimesh.creation.box(extents=(0.5, 0.7, 0.05),
                                 transform=trimesh.transformations.translation_matrix((0, 0, -0.1)))
    body = trimesh.util.concatenate([arm, ball, torso])
    return faces, uv, gt, inferred, (np.asarray(body.vertices, np.float64), np.asarray(body.faces, np.int64))


@pytest.fixture(scope="module")
def oblique():
    return look_at("oblique", (0.7, 0.15, 1.3), (0, 0, 0), width=200, height=200, focal=260.0)


@pytest.mark.slow
@pytest.mark.parametrize("subdiv", [0, 1])
def test_body_hits_equal_brute_force_ray_cast(gl, oblique, subdiv):
    """Every assigned vertex: nothing (cloth or body) before it on its ray, its first hit
    among gt cloth and body is gt cloth, and d is that hit's uv; the vertices the body
    hides (or whose gt material it hides) are many, and unassigned."""
    faces, uv, gt, inferred, (body_positions, body_faces) = worn_folded_sheet()
    sub = subdivide(faces, len(uv), subdiv)
    d, assigned = slide_pose(gt, inferred, faces, uv, oblique, sub, SlideOptions(subdiv=subdiv),
                             body=(body_positions, body_faces))
    X = apply_parent(inferred, sub.parent)
    uv_sub = apply_parent(uv.astype(np.float64), sub.parent)
    origin = oblique.center
    dirs = X - origin
    # Independent: every triangle of cloth and body, no raster.
    occ_tri, occ_t, _ = brute_force_first_hit(origin, dirs, np.concatenate([X, body_positions]),
                                              np.concatenate([sub.faces, body_faces + len(X)]))
    gt_tri, _, gt_bary = brute_force_first_hit(origin, dirs, np.concatenate([gt, body_positions]),
                                               np.concatenate([faces, body_faces + len(gt)]))
    by_body = (occ_t < 1 - 1e-3) & (occ_tri >= len(sub.faces)) | (gt_tri >= len(faces))
    idx = np.flatnonzero(assigned)
    assert np.mean(occ_t[idx] >= 1 - 1e-3) >= 0.995
    on_cloth = (gt_tri[idx] >= 0) & (gt_tri[idx] < len(faces))
    assert np.mean(on_cloth) >= 0.995
    ok = idx[on_cloth]
    t_n = np.einsum("kj,kjc->kc", gt_bary[ok], uv[faces[gt_tri[ok]]].astype(np.float64))
    assert np.mean(np.abs(d[ok] - (t_n - uv_sub[ok])).max(axis=1) <= 1e-5) >= 0.995
    assert by_body.sum() > 0.05 * len(X)
    assert np.sum(assigned & by_body) <= 0.005 * by_body.sum()


@pytest.mark.parametrize("radius", [0, 1, 2])
def test_body_compiled_search_equals_numpy_search(gl, oblique, radius):
    """With a body, the compiled kernels and the NumPy formulation agree bit for bit."""
    faces, uv, gt, inferred, (body_positions, body_faces) = worn_folded_sheet()
    options = SlideOptions(subdiv=1, radius=radius)
    topo = build_topology(faces, uv, gt, 1)
    body = (body_positions, body_topology(body_faces, topo))
    X = topo.positions(inferred)
    faces = faces.astype(np.int64)
    compiled, numpy_hits = [find_hits_raster(gl, gt, inferred, faces, X, topo, oblique, options,
                                             compiled=c, body=body) for c in (True, False)]
    for field in ("visible", "tri", "bary", "back", "from_inside"):
        assert np.array_equal(getattr(compiled, field), getattr(numpy_hits, field)), field
    plain = find_hits_raster(gl, gt, inferred, faces, X, topo, oblique, options)
    assert compiled.visible.sum() < plain.visible.sum()


def test_body_raster_path_equals_embree_ray_cast(gl, oblique):
    """The raster path and the Embree ray cast (the body in each of its scenes) give the
    same visibility and the same hits, up to float32 grazing rays at edges."""
    pytest.importorskip("embreex")
    from mvtex.apps.bench import find_hits_embree

    faces, uv, gt, inferred, (body_positions, body_faces) = worn_folded_sheet()
    options = SlideOptions(subdiv=1)
    topo = build_topology(faces, uv, gt, 1)
    body = (body_positions, body_topology(body_faces, topo))
    X = topo.positions(inferred)
    faces = faces.astype(np.int64)
    raster = find_hits_raster(gl, gt, inferred, faces, X, topo, oblique, options, body=body)
    embree = find_hits_embree(gt, inferred, faces, X, topo, oblique, options, body=body)
    assert np.mean(raster.visible == embree.visible) >= 0.995
    both = raster.visible & embree.visible
    assert np.mean(raster.tri[both] == embree.tri[both]) >= 0.995
    hit = both & (raster.tri == embree.tri) & (raster.tri >= 0)
    assert np.abs(raster.bary[hit] - embree.bary[hit]).max() < 1e-6
    plain = find_hits_embree(gt, inferred, faces, X, topo, oblique, options)
    assert embree.visible.sum() < plain.visible.sum()


def test_raster_marks_body_pixels(gl, front):
    """`rasterize(..., occluder=)`: a pixel whose ray meets the box is body, not cloth; the
    others show the sheet as without a body (closed form per pixel centre)."""
    from mvtex.render.raster import rasterize

    faces, uv, gt = grid_mesh(31, 31)
    box = box_mesh(*BOX)
    with_body = rasterize(gl, gt, faces, front, occluder=box)
    plain = rasterize(gl, gt, faces, front)
    assert plain.body is None
    v, u = np.mgrid[0:front.height, 0:front.width]
    rays = front.pixel_rays(np.stack([u.ravel(), v.ravel()], 1).astype(np.float64))
    far = CENTRE + 10 * rays / np.linalg.norm(rays, axis=1, keepdims=True)
    lo, hi = BOX
    inside = segment_meets_box(CENTRE, far, lo + 0.002, hi - 0.002).reshape(front.height, front.width)
    outside = ~segment_meets_box(CENTRE, far, lo - 0.002, hi + 0.002).reshape(front.height, front.width)
    assert inside.sum() > 500
    assert with_body.body[inside].all() and not with_body.body[outside].any()
    assert (with_body.tri_id[inside] == -1).all()
    assert np.array_equal(with_body.tri_id[outside], plain.tri_id[outside])
    assert np.array_equal(with_body.depth[outside], plain.depth[outside])


# The body's edges: cases the raster cannot resolve, decided by the exact rule (a vertex is
# hidden when its ray meets the body before it; a gt hit, when the body comes first).

STRIP_X = 0.05  # a ray to a sheet vertex at x = 0.1 crosses z = 1 at x = 0.05 (camera at z = 2)


def _sheet_with_body(gl, front, body, case, subdiv):
    """slide_pose of the flat 31 x 31 sheet (vertices every 2 cm; at x = 0.1 they project to
    u = 99.5, between pixel centres) with `body`: the inferred sheet is gt itself or gt
    moved towards the camera on the same rays. Returns (gt positions of the subdivided
    vertices, d, assigned)."""
    faces, uv, gt = grid_mesh(31, 31)
    inferred = gt if case == "hides the vertex" else CENTRE + 0.3 * (gt - CENTRE)
    sub = subdivide(faces, len(uv), subdiv)
    d, assigned = slide_pose(gt, inferred, faces, uv, front, sub, SlideOptions(subdiv=subdiv), body=body, ctx=gl)
    return apply_parent(gt, sub.parent), d, assigned


@pytest.mark.parametrize("subdiv", [0, 1])
@pytest.mark.parametrize("case", ["hides the vertex", "hides the gt cloth"])
def test_a_body_that_no_pixel_centre_sees(gl, front, case, subdiv):
    """A thin box (0.5 mm wide, 1 cm deep) whose projection lies between two pixel
    columns: the raster shows none of it, so no raster window holds its faces, yet it hides
    the column of vertices at x = 0.1 (closed form). Exactly those are unassigned."""
    from mvtex.render.raster import rasterize

    lo, hi = np.array([STRIP_X - 2.5e-4, -0.2, 0.99]), np.array([STRIP_X + 2.5e-4, 0.2, 1.0])
    body = box_mesh(lo, hi)
    faces, _, gt = grid_mesh(31, 31)
    assert not rasterize(gl, gt, faces, front, occluder=body).body.any()  # no pixel shows it
    points, d, assigned = _sheet_with_body(gl, front, body, case, subdiv)
    hidden = segment_meets_box(CENTRE, points, lo, hi)
    assert hidden.sum() >= 31
    assert np.array_equal(assigned, ~hidden)
    assert np.abs(d[assigned]).max() < 1e-6


@pytest.mark.parametrize("inside", [True, False])
def test_a_ray_grazing_a_box_edge(gl, front, inside):
    """The box's top edge lies 1e-7 m beside the rays to the column of vertices at x = 0.1
    (far below a pixel): on the inside they meet the box's top face and are hidden, on the
    outside they pass it and are assigned, as the closed form says for every vertex."""
    delta = 1e-7 if inside else -1e-7
    lo, hi = np.array([0.015, -0.2, 0.9]), np.array([STRIP_X + delta, 0.2, 1.0])
    points, d, assigned = _sheet_with_body(gl, front, box_mesh(lo, hi), "hides the vertex", 1)
    hidden = segment_meets_box(CENTRE, points, lo, hi)
    column = np.abs(points[:, 0] - 2 * STRIP_X) < 1e-9
    assert column.sum() == 61 and np.all(hidden[column] == inside)
    assert np.array_equal(assigned, ~hidden)
    assert np.abs(d[assigned]).max() < 1e-6


@pytest.mark.parametrize("gt_lift", [0.0, 0.002])
def test_a_vertex_inside_the_body(gl, front, gt_lift):
    """The inferred sheet cuts into three small boxes (8 mm wide, their top 0.5 mm above
    it) around three of its vertices: those are inside the body, hidden from the camera,
    although the body is nearer by less than the cloth's own depth tolerance and their
    faces still own pixels around the boxes, and although the gt sheet (lifted 2 mm, out
    of the boxes) meets the ray before the body. The body has no tolerance: exactly the
    vertices the closed form hides are unassigned."""
    centres = np.array([[-0.1, -0.1], [0.0, 0.04], [0.12, -0.06]])
    boxes = [(np.r_[c - 0.004, -0.01], np.r_[c + 0.004, 0.0005]) for c in centres]
    parts = [box_mesh(lo, hi) for lo, hi in boxes]
    body = (np.concatenate([p for p, _ in parts]), np.concatenate([f + 8 * i for i, (_, f) in enumerate(parts)]))
    faces, uv, inferred = grid_mesh(31, 31)
    gt = inferred + [0.0, 0.0, gt_lift]
    sub = subdivide(faces, len(uv), 1)
    d, assigned = slide_pose(gt, inferred, faces, uv, front, sub, SlideOptions(subdiv=1), body=body, ctx=gl)
    points = apply_parent(inferred, sub.parent)
    hidden = np.any([segment_meets_box(CENTRE, points, lo, hi) for lo, hi in boxes], axis=0)
    inside = np.any([np.all((points > lo) & (points < hi), axis=1) for lo, hi in boxes], axis=0)
    assert inside.sum() == 3 and (hidden == inside).all()
    assert np.array_equal(assigned, ~hidden)
    # d is the gt hit's uv: the ray to (x, y, 0) meets z = lift at (x, y) (1 - lift / 2).
    expected = -points[:, :2] * gt_lift / 2 / 0.6
    assert np.abs(d[assigned] - expected[assigned]).max() < 1e-6


@pytest.mark.parametrize("compiled", [True, False])
def test_nearest_body_hit_equals_brute_force(compiled, oblique):
    """`nearest_body_hit` (faces binned by projection) gives every ray the t of a float64
    ray cast against every face of the body (to rounding), also for points behind the
    camera and for a body face reaching behind it."""
    from mvtex.sliding.hits import nearest_body_hit

    *_, (body_positions, body_faces) = worn_folded_sheet()
    rng = np.random.default_rng(3)
    points = np.concatenate([rng.uniform(-0.4, 0.4, (3000, 3)), oblique.center + rng.normal(0, 0.3, (200, 3))])
    # A face through the camera's plane.
    reach = np.array([oblique.center + (0.1, 0.0, -0.3), oblique.center + (-0.1, 0.05, 0.3),
                      oblique.center + (0.0, -0.1, 0.3)])
    positions = np.concatenate([body_positions, reach])
    faces = np.concatenate([body_faces, [[len(body_positions), len(body_positions) + 1, len(body_positions) + 2]]])
    t = nearest_body_hit(oblique, positions, faces, points, compiled=compiled)
    dirs = points - oblique.center
    _, t_ref, _ = brute_force_first_hit(oblique.center, dirs, positions, faces)
    from mvtex.sliding.hits import bin_body

    pixels, z = oblique.project(points)
    seen = (z > 0) & oblique.in_image(pixels, z)
    bins = [bin_body(oblique, positions, faces, pixels[seen], compiled=c) for c in (True, False)]
    for field in ("start", "faces", "everywhere"):
        assert np.array_equal(getattr(bins[0], field), getattr(bins[1], field)), field
    assert len(bins[0].everywhere) == 1
    finite = np.isfinite(t_ref)
    assert finite.sum() > 1000 and (t_ref < 1).sum() > 200 and (t_ref[-200:] < np.inf).sum() > 10
    assert np.array_equal(np.isfinite(t), finite)
    assert np.abs(t[finite] - t_ref[finite]).max() <= 1e-12 * t_ref[finite].max()


@pytest.mark.slow
def test_worn_shirt_seen_into_its_openings_against_embree(gl):
    """The built-in T-shirt with its body, seen by cameras looking into its collar and its
    hem: no vertex that `slide` assigns is hidden by the body per an Embree ray cast (float32
    hits re-intersected in float64, benchmarks/body_hidden.py), and many are hidden."""
    pytest.importorskip("embreex")
    import importlib.util
    from pathlib import Path

    from mvtex.synth.generate import SynthOptions, synthesize

    spec = importlib.util.spec_from_file_location(
        "body_hidden", Path(__file__).resolve().parents[2] / "benchmarks" / "body_hidden.py")
    reference = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(reference)
    data = synthesize(SynthOptions(num_poses=3, seed=0))
    faces = np.asarray(data["faces"], np.int64)
    body_faces = np.asarray(data["body_faces"], np.int64)
    topo = build_topology(faces, data["uv"], np.asarray(data["rest"], np.float64), 1)
    body_topo = body_topology(body_faces, topo)
    rings = reference.vertex_ring(faces), reference.vertex_ring(body_faces)
    hidden_total = 0
    for k in range(3):
        gt = np.asarray(data["gt"][k], np.float64)
        inferred = np.asarray(data["inferred"][k], np.float64)
        body_positions = np.asarray(data["body"][k], np.float64)
        X = topo.positions(inferred)
        for cam in reference.openings_rig(gt):
            _, assigned = slide_pose(gt, inferred, faces, data["uv"], cam, topo.subdivision, SlideOptions(subdiv=1),
                                     topology=topo, ctx=gl, body=(body_positions, body_faces), body_topo=body_topo)
            hidden = reference.body_hidden(cam, X, gt, faces, rings[0], body_positions, body_faces, rings[1])["hidden"]
            assert not np.any(assigned & hidden), (k, cam.name, np.flatnonzero(assigned & hidden))
            assert assigned.sum() > 0.1 * len(X)
            hidden_total += int(hidden.sum())
    assert hidden_total > 10000
