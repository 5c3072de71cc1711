"""The GL rasterizer against independent numpy computations (projection, exact ray cast)."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import grid_mesh, wave

from mvtex.data.camera import look_at
from mvtex.render.raster import interpolate, rasterize, rasterize_uv
from mvtex.render.shading import render_textured

pytestmark = pytest.mark.gl


def ray_cast_nearest(origin, dirs, positions, faces):
    """Brute-force float64 Möller–Trumbore: nearest hit triangle (-1 if none) and distance."""
    p = positions[faces]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    best = np.full(len(dirs), -1)
    best_t = np.full(len(dirs), np.inf)
    for k, d in enumerate(dirs):
        h = np.cross(d, e2)
        a = np.einsum("ij,ij->i", e1, h)
        with np.errstate(divide="ignore", invalid="ignore"):
            f = 1.0 / a
            s = origin - p[:, 0]
            u = f * np.einsum("ij,ij->i", s, h)
            q = np.cross(s, e1)
            v = f * (q @ d)
            t = f * np.einsum("ij,ij->i", e2, q)
        ok = (np.abs(a) > 1e-15) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        if ok.any():
            i = np.flatnonzero(ok)[np.argmin(t[ok])]
            best[k], best_t[k] = i, t[i]
    return best, best_t


@pytest.fixture(scope="module")
def scene(gl):
    faces, uv, rest = grid_mesh(30, 26)
    positions = wave(rest, 0.03, 0.4)
    cam = look_at("c", (0.35, 0.25, 1.1), (0, 0, 0), width=200, height=150, focal=240.0)
    return positions, faces, uv, cam


def test_bary_point_projects_to_pixel_centre_and_reproduces_depth(gl, scene):
    import cv2

    positions, faces, uv, cam = scene
    r = rasterize(gl, positions, faces, cam)
    rows, cols = np.nonzero(r.mask)
    assert len(rows) > 5000
    X = np.einsum("kj,kjc->kc", r.bary[rows, cols].astype(np.float64), positions[faces[r.tri_id[rows, cols]]])
    pix, _ = cv2.projectPoints(X, cv2.Rodrigues(cam.R)[0], cam.t, cam.K, None)
    assert np.abs(pix.reshape(-1, 2) - np.stack([cols, rows], 1)).max() <= 0.01
    z = (X @ cam.R.T + cam.t)[:, 2]
    assert np.abs(z - r.depth[rows, cols]).max() <= 1e-5 * z.max()
    # GL snaps vertices to 1/256 px: pixel centres within that of an edge may get tiny negative weights.
    assert np.all(r.bary[r.mask] >= -1e-3) and np.allclose(r.bary[r.mask].sum(-1), 1, atol=1e-5)


def test_vertices_land_where_opencv_projects_them(gl, scene):
    """A vertex moved to 0.2 px from a pixel centre has that pixel drawn by one of its own
    triangles (unless something is in front of it): it lands where OpenCV projects it."""
    import cv2

    positions, faces, uv, cam = scene
    r = rasterize(gl, positions, faces, cam)
    pix, _ = cv2.projectPoints(positions, cv2.Rodrigues(cam.R)[0], cam.t, cam.K, None)
    pix = pix.reshape(-1, 2)
    col, row = np.arange(len(positions)) % 30, np.arange(len(positions)) // 30
    inside_sheet = (col > 0) & (col < 29) & (row > 0) & (row < 25)  # border vertices have no full one-ring
    interior = inside_sheet & (pix[:, 0] > 2) & (pix[:, 1] > 2) & (pix[:, 0] < cam.width - 3) & (pix[:, 1] < cam.height - 3)
    rng = np.random.default_rng(0)
    idx = rng.choice(np.flatnonzero(interior), 40, replace=False)
    target = np.round(pix[idx]) + 0.2
    rays = cam.pixel_rays(target)
    depth = (positions[idx] @ cam.R.T + cam.t)[:, 2]
    moved = positions.copy()
    moved[idx] = cam.center + rays * (depth / (rays @ cam.R[2]))[:, None]
    r = rasterize(gl, moved, faces, cam)
    centre = np.round(target).astype(int)
    hit_incident = [np.any(faces[r.tri_id[v, u]] == i) for i, (u, v) in zip(idx, centre)]
    _, t_ray = ray_cast_nearest(cam.center, rays, moved, faces)
    unoccluded = t_ray >= np.linalg.norm(moved[idx] - cam.center, axis=1) - 1e-7
    assert unoccluded.sum() > 20
    assert all(h for h, ok in zip(hit_incident, unoccluded) if ok)


def test_tri_id_matches_exact_ray_cast(gl, scene):
    positions, faces, uv, cam = scene
    r = rasterize(gl, positions, faces, cam)
    rng = np.random.default_rng(1)
    rows = rng.integers(0, cam.height, 600)
    cols = rng.integers(0, cam.width, 600)
    dirs = cam.pixel_rays(np.stack([cols, rows], 1).astype(np.float64))
    ref, _ = ray_cast_nearest(cam.center, dirs, positions, faces)
    got = r.tri_id[rows, cols]
    # Background is -1 exactly where the exact ray misses everything.
    assert np.array_equal(got == -1, ref == -1) or np.mean((got == -1) != (ref == -1)) < 0.005
    both = (got >= 0) & (ref >= 0)
    assert np.mean(got[both] == ref[both]) > 0.99
    assert np.all(r.depth[~r.mask] == 0) and np.all(r.bary[~r.mask] == 0)


def test_occluder_hides_what_is_behind(gl):
    faces, uv, rest = grid_mesh(10, 10, size=0.5)
    occluder_faces, _, occ = grid_mesh(4, 4, size=0.1)
    occ = occ + np.array([0.0, 0.0, 0.2])  # 20 cm in front of the sheet
    positions = np.concatenate([rest, occ])
    all_faces = np.concatenate([faces, occluder_faces + len(rest)])
    cam = look_at("c", (0, 0, 1.0), (0, 0, 0), width=120, height=120, focal=150.0)
    r = rasterize(gl, positions, all_faces, cam)
    centre = r.tri_id[55:65, 55:65]
    assert np.all(centre >= len(faces))  # the occluder owns the middle
    assert np.allclose(r.depth[55:65, 55:65], 0.8, atol=1e-5)
    corner = r.tri_id[30, 30]
    assert 0 <= corner < len(faces)
    # Drawing order does not matter: the depth test decides.
    r2 = rasterize(gl, positions, np.concatenate([occluder_faces + len(rest), faces]), cam)
    assert np.all(r2.tri_id[55:65, 55:65] < len(occluder_faces))


def test_uv_raster_recovers_texel_centres(gl):
    faces, uv, rest = grid_mesh(9, 7)
    W, H = 64, 48
    r = rasterize_uv(gl, uv, faces, W, H)
    rows, cols = np.nonzero(r.mask)
    assert r.mask.mean() > 0.9
    got = interpolate(uv, r, faces)[rows, cols]
    expected = np.stack([(cols + 0.5) / W, (rows + 0.5) / H], axis=1)
    assert np.abs(got - expected).max() < 1e-5


def test_textured_render_shows_the_texture(gl, scene):
    positions, faces, uv, cam = scene
    image = render_textured(gl, positions, faces, uv, cam)
    assert image.shape == (cam.height, cam.width, 3) and image.dtype == np.uint8
    mask = rasterize(gl, positions, faces, cam).mask
    assert image[mask].std() > 10  # a pattern, not a flat colour
    assert np.all(image[~mask & ~np.roll(mask, 1, 0) & ~np.roll(mask, -1, 0) & ~np.roll(mask, 1, 1) & ~np.roll(mask, -1, 1)] == [40, 40, 46])
    slid = render_textured(gl, positions, faces, uv + np.float32([0.01, 0.0]), cam)
    assert np.abs(slid.astype(int) - image.astype(int))[mask].mean() > 3  # sliding is visible


def test_distortion_is_refused(gl, scene):
    from mvtex.data.camera import Camera

    positions, faces, uv, cam = scene
    bad = Camera("d", cam.width, cam.height, K=cam.K, R=cam.R, t=cam.t, dist=[0.1, 0, 0, 0, 0])
    with pytest.raises(ValueError, match="distortion"):
        rasterize(gl, positions, faces, bad)


def test_consecutive_renders_leave_gl_clean(gl, scene):
    positions, faces, uv, cam = scene
    a = render_textured(gl, positions, faces, uv, cam)
    rasterize(gl, positions, faces, cam)
    b = render_textured(gl, positions, faces, uv, cam)
    assert np.array_equal(a, b)
    assert gl.error == "GL_NO_ERROR"


def test_empty_mesh_is_all_background(gl, scene):
    positions, faces, uv, cam = scene
    r = rasterize(gl, positions, faces[:0], cam)
    assert np.all(r.tri_id == -1) and np.all(r.depth == 0)
