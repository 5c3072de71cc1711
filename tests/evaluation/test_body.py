"""The body in the per-pixel errors (DESIGN §5 "The body"): pixels where the body hides the
cloth of one render leave the metric; the share they take is reported. Checked against
rasters without a body and the box's pixels in closed form."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from helpers import grid_mesh

from mvtex.data.dataset import save_dataset
from mvtex.data.texcoords import save_texcoords
from mvtex.evaluation.evaluate import evaluate
from mvtex.render.raster import rasterize

pytestmark = pytest.mark.gl

# Between the gt sheet (z = 0) and the inferred sheet (z = 2 cm, towards the cameras): the
# gt render shows the box there, the inferred render its cloth.
BOX = (np.array([-0.12, -0.05, 0.006]), np.array([0.04, 0.09, 0.014]))


def pixel_rays_meet_box(camera, lo, hi):
    """(H,W) bool: the ray through each pixel centre meets the box (slab method)."""
    v, u = np.mgrid[0:camera.height, 0:camera.width]
    d = camera.pixel_rays(np.stack([u.ravel(), v.ravel()], 1).astype(np.float64))
    o = camera.center
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (lo - o) / d, (hi - o) / d
    near = np.nanmax(np.minimum(t0, t1), axis=1)
    far = np.nanmin(np.maximum(t0, t1), axis=1)
    return ((near <= far) & (far > 0)).reshape(camera.height, camera.width)


def test_pixels_the_body_hides_leave_the_metric(gl, front_rig, tmp_path):
    faces, uv, rest = grid_mesh(40, 40)
    gt = rest.astype(np.float32)
    # The inferred material slides most where the box is: leaving those pixels out matters.
    bump = 0.02 * np.exp(-((rest[:, 0] + 0.04) ** 2 + (rest[:, 1] - 0.02) ** 2) / 0.01)
    inferred = (rest + [0.004, 0.002, 0.02] + bump[:, None] * [1, 0, 0]).astype(np.float32)
    lo, hi = BOX
    box = trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((lo + hi) / 2))
    body_faces, body = np.asarray(box.faces, np.int32), np.asarray(box.vertices, np.float32)[None]
    for name, extra in (("plain", {}), ("worn", {"body_faces": body_faces, "body": body})):
        save_dataset(tmp_path / name, faces=faces, uv=uv, gt=gt[None], inferred=inferred[None],
                     poses=np.zeros((1, 1)), rest=rest, **extra)
    tc = save_texcoords(tmp_path / "tc", faces=faces, uv=uv, parent=np.stack([np.arange(len(uv))] * 2, 1),
                        source="test", subdiv=0, poses=[0],
                        displacement={c.name: np.full((1, len(uv), 2), 0.003, np.float32) for c in front_rig},
                        assigned={c.name: np.ones((1, len(uv)), bool) for c in front_rig})
    plain = evaluate(tmp_path / "plain", front_rig, tc, progress=False)
    worn = evaluate(tmp_path / "worn", front_rig, tc, progress=False)
    assert plain.body_share is None and plain.to_json()["body_share"] is None
    for cam in front_rig:
        # Independent: rasters without a body, uv interpolated here, the box in closed form.
        r_g, r_i = rasterize(gl, gt, faces, cam), rasterize(gl, inferred, faces, cam)
        uv_g = np.einsum("hwj,hwjc->hwc", r_g.bary.astype(np.float64), uv[faces[r_g.tri_id]].astype(np.float64))
        uv_i = np.einsum("hwj,hwjc->hwc", r_i.bary.astype(np.float64), uv[faces[r_i.tri_id]].astype(np.float64))
        e = np.linalg.norm(uv_i - uv_g, axis=2)
        hidden = pixel_rays_meet_box(cam, lo, hi)
        g_cloth, i_cloth = (r_g.tri_id >= 0) & ~hidden, r_i.tri_id >= 0
        assert (hidden & i_cloth).sum() > 300
        expected = np.sqrt(np.mean(e[g_cloth & i_cloth] ** 2))
        everywhere = np.sqrt(np.mean(e[(r_g.tri_id >= 0) & i_cloth] ** 2))
        share = (hidden & (r_g.tri_id >= 0) & i_cloth).sum() / (g_cloth | i_cloth).sum()
        per = worn.per_camera[cam.name]
        # Pixel centres on the box's outline may go either way: a few pixels of hundreds.
        assert per.sqrt_mse.inferred.mean == pytest.approx(expected, rel=2e-3)
        assert per.body_share.mean == pytest.approx(share, rel=2e-2)
        assert plain.per_camera[cam.name].sqrt_mse.inferred.mean == pytest.approx(everywhere, rel=1e-5)
        assert abs(expected - everywhere) > 0.1 * everywhere  # the box changes the answer
