"""Texture coordinates of novel views between the cameras of an array (DESIGN §5 "Novel
views"); the novel cameras themselves are `mvtex.views.cameras.interpolate_camera`'s.

Two methods:

- ``blend`` (the paper): T_N(v) = Σ w_p T_N(v_p), i.e. d(v) = Σ w_p d(v_p). A vertex is
  `assigned` where every camera with w_p > 0 assigned it (its d came from rays only).
- ``reconstruct`` (beyond the paper): triangulate the pose from the array cameras'
  texcoords (`mvtex.recon.triangulate.reconstruct`), texture-slide the inferred mesh against that
  reconstruction from the novel camera itself (`mvtex.sliding.pose.slide_pose`, the
  reconstruction standing in for the gt mesh): the slide only says where the view's ray
  through a vertex meets the cloth (point P); the material there is read from the array
  cameras that see P (their own texcoords at P's projection), weighted by w_p. A depth
  error of P shifts its projection only by the baseline angle, so the reconstruction's
  error is damped. Where nothing better is known (no hit, no camera sees P) the blend is
  kept. Works from TS and TSNN texcoords alike: no gt is read.

For both methods a view with weight 1 on one camera gets that camera's texcoords bit for
bit: the view is that camera, and its texcoords are the measured ones.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from mvtex.data.camera import Camera
from mvtex.data.dataset import reference_shape
from mvtex.data.mesh import charts_through_parent, uv_charts
from mvtex.data.rig import Rig
from mvtex.recon.locate import locate_uv
from mvtex.recon.triangulate import ReconOptions, reconstruct
from mvtex.render.context import GLContext
from mvtex.render.raster import rasterize
from mvtex.sliding.hits import intersect_pairs
from mvtex.sliding.options import SlideOptions
from mvtex.sliding.pose import slide_pose
from mvtex.sliding.topology import body_topology, build_topology
from mvtex.util.errors import InputError
from mvtex.util.files import read_row
from mvtex.views.cameras import _single
from mvtex.views.options import ViewOptions

# A point counts as seen by an array camera when it is no deeper than the farthest
# reconstructed surface around its projection, with this relative slack (4 mm at 2 m).
_VISIBILITY_TOLERANCE = 2e-3


def blend_displacement(displacements: Mapping[str, np.ndarray], assigned: Mapping[str, np.ndarray],
                       weights: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """d(v) = Σ w_p d(v_p); assigned where every camera with w_p > 0 assigned the vertex.

    Args:
        displacements: camera -> (n',2) float32; assigned: camera -> (n',) bool.
        weights: camera -> weight.

    Returns:
        d (n',2) float32 and assigned (n',) bool; a weight of 1 returns copies of that
        camera's arrays (bit for bit).
    """
    one = _single(weights)
    if one is not None:
        return np.array(displacements[one], np.float32), np.array(assigned[one], bool)
    names = [k for k, w in weights.items() if w > 0]
    d = np.zeros(np.shape(displacements[names[0]]), np.float64)
    a = np.ones(np.shape(assigned[names[0]]), bool)
    for k in names:
        d += float(weights[k]) * np.asarray(displacements[k], np.float64)
        a &= np.asarray(assigned[k], bool)
    return d.astype(np.float32), a


@dataclass
class PoseContext:
    """What one pose's novel views share: the array's texcoords and, for "reconstruct",
    the reconstruction of the pose and the sliding topology.

    Attributes:
        displacement, assigned: array camera -> (n',2) float32 / (n',) bool.
        inferred: (n,3) float64 inferred positions X_N of the pose.
        reconstruction: `mvtex.recon.triangulate.Reconstruction` or None (method "blend").
        body: (positions, faces) of the dataset's body in the pose, or None.
        cache: per array camera, its rasters of the inferred and reconstructed meshes (and the body).
    """

    pose: int
    displacement: dict[str, np.ndarray]
    assigned: dict[str, np.ndarray]
    inferred: np.ndarray
    reconstruction: object | None = None
    body: tuple[np.ndarray, np.ndarray] | None = None
    cache: dict | None = None


class ViewSynthesizer:
    """Texcoords of novel views for the poses of one texcoord set.

    Args:
        dataset: a `Dataset` (only its mesh, inferred positions and rest shape are read).
        rig: the array's rig (must hold the texcoord set's cameras).
        texcoords: a `TexcoordSet` of the array.
        options: ViewOptions.
    """

    def __init__(self, dataset, rig: Rig, texcoords, options: ViewOptions = ViewOptions(), ctx=None):
        texcoords.check_rig(rig)
        texcoords.check_dataset(dataset)

        self.dataset = dataset
        self._owns_gl = ctx is None
        self.gl = GLContext() if ctx is None else ctx
        self.rig = rig
        self.texcoords = texcoords
        self.options = options
        self.array = [c for c in texcoords.cameras if c in rig.names]
        self._topology = None
        self._slide_options = None

        # With two cameras a vertex needs both observations: hypotheses in triangles with
        # extrapolated corners are kept (the triangulation's reprojection and surface checks
        # still reject bad ones). With more cameras dropping them leaves enough. Measured on
        # the built-in garment (same-chart SqrtMSE e-3): stereo midpoint 0.471 -> 0.438 when
        # kept; square4 3x3 grid mean 0.365 when dropped, 0.385 when kept.
        self.recon_options = ReconOptions(require_assigned=len(self.array) > 2)

    def release(self) -> None:
        """Free the GL context if this object made it."""
        if self._owns_gl:
            self.gl.release()

    def __enter__(self) -> "ViewSynthesizer":
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    # the sliding machinery, built once
    def _sliding(self):
        if self._topology is None:

            tc = self.texcoords
            recorded = tc.meta.get("options") if isinstance(tc.meta.get("options"), dict) else {}
            known = {k: v for k, v in recorded.items() if k in SlideOptions.__dataclass_fields__}
            known["subdiv"] = tc.subdiv
            self._slide_options = SlideOptions(**known)
            ds = self.dataset

            self._topology = build_topology(ds.faces, ds.uv, reference_shape(ds), tc.subdiv)
            if len(self._topology.uv) != len(tc.uv):
                raise InputError(tc.path / "mesh.npz", f"{len(tc.uv)} vertices, but {tc.subdiv} subdivision(s) of the "
                                 f"dataset's mesh give {len(self._topology.uv)}")
        return self._topology, self._slide_options

    def prepare(self, pose: int, progress: bool = False) -> PoseContext:
        """Load the array's texcoords of a pose and, for "reconstruct", triangulate it."""
        tc = self.texcoords
        state = PoseContext(pose=int(pose),
                          displacement={c: tc.displacement(c, pose) for c in self.array},
                          assigned={c: tc.assigned(c, pose) for c in self.array},
                          inferred=read_row(self.dataset.inferred, pose).astype(np.float64),
                          body=None if self.dataset.body is None else (self.dataset.body.pose(pose),
                                                                       self.dataset.body.faces))
        if self.options.method == "reconstruct":

            if len(self.array) < 2:
                raise InputError(tc.path, "method reconstruct needs texcoords of at least 2 rig cameras "
                                 f"(the set has {', '.join(tc.cameras)})")
            X_N = tc.positions(state.inferred)
            T = {c: tc.uv.astype(np.float64) + state.displacement[c] for c in self.array}
            state.reconstruction = reconstruct(self.dataset.uv, X_N, tc.faces, tc.uv, T, self.rig.select(self.array),
                                             self.recon_options.for_source(tc.source), gt_faces=self.dataset.faces, assigned=state.assigned,
                                             body=state.body, progress=progress, ctx=self.gl)
        return state

    def view(self, state: PoseContext, camera: Camera, weights: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray]:
        """d (n',2) float32 and assigned (n',) bool of one novel view at a prepared pose.

        Args:
            camera: the view's camera (need not be `interpolate_camera(weights)`: preview's
                eyes sit off the array's span). weights: array camera -> weight, used by
                the blend and, for "reproject", to weight the cameras that see a point.
        """
        d_blend, a_blend = blend_displacement(state.displacement, state.assigned, weights)
        if self.options.method == "blend" or (_single(weights) is not None and
                                              np.array_equal(camera.R, self.rig[_single(weights)].R) and
                                              np.array_equal(camera.t, self.rig[_single(weights)].t)):
            return d_blend, a_blend

        topo, slide_options = self._sliding()
        rec = state.reconstruction
        d_rec, a_rec = slide_pose(rec.points, state.inferred, self.dataset.faces, self.dataset.uv, camera,
                                  topo.subdivision, slide_options, topology=topo, ctx=self.gl, body=state.body,
                                  body_topo=self._body_topology())
        return self._reproject(state, camera, weights, d_rec, a_rec, d_blend, a_blend)

    def _body_topology(self):
        if self.dataset.body is None:
            return None
        if getattr(self, "_body_topo", None) is None:

            self._body_topo = body_topology(self.dataset.body.faces, self._sliding()[0])
        return self._body_topo

    def _hit_points(self, d_rec: np.ndarray, a_rec: np.ndarray, points: np.ndarray):
        """Where the slide against the reconstruction hit it, found from the slid uv (the
        reconstruction carries T_G): (k,) vertex indices, (k,3) hit points P, (k,) hit face
        of the base mesh."""

        faces = np.asarray(self.dataset.faces, np.int64)
        hit_uv = self.texcoords.uv.astype(np.float64) + d_rec
        idx = np.flatnonzero(a_rec)
        point, face, bary = locate_uv(hit_uv[idx], faces, self.dataset.uv, self.options.uv_resolution, ctx=self.gl)
        first = np.r_[True, point[1:] != point[:-1]] if len(point) else np.zeros(0, bool)
        point, face, bary = point[first], face[first], bary[first]
        xyz = np.einsum("kj,kjc->kc", bary, points[faces[face]])
        return idx[point], xyz, face

    def _reproject(self, state: PoseContext, camera: Camera, weights, d_rec, a_rec, d_blend, a_blend):
        """The material the array cameras show where the view's rays meet the reconstruction.

        For vertex i the view's ray through X_N(i) meets the reconstructed surface at P
        (from the slide against it). Array camera p shows at P's projection the material
        T_N^p of the inferred surface point its ray through P meets (exact ray/triangle
        intersection, candidates from p's raster); the view takes Σ w_p of those over the
        cameras that see P (depth test against the reconstruction seen from p), in P's
        chart, renormalised. A depth error of P moves P's projection in camera p only by its
        component across p's ray (the baseline angle), so the reconstruction's error is
        damped; where no weighted camera sees P, the blend.
        """

        rec = state.reconstruction
        tc = self.texcoords
        sub_faces = np.asarray(tc.faces, np.int64)
        verts, P, hit_face = self._hit_points(d_rec, a_rec, rec.points)
        if state.cache is None:
            state.cache = {}
        X_sub = tc.positions(state.inferred)
        chart_sub, chart_gt = self._charts()
        keep = chart_gt[hit_face] == chart_sub[verts]
        verts, P = verts[keep], P[keep]
        total_w = np.zeros(len(verts))
        total_uv = np.zeros((len(verts), 2))
        for name, w in weights.items():
            if w <= 0:
                continue
            cam = self.rig[name]
            if name not in state.cache:
                state.cache[name] = (rasterize(self.gl, X_sub, sub_faces, cam),
                                     rasterize(self.gl, rec.points, self.dataset.faces, cam),
                                     None if state.body is None else rasterize(self.gl, *state.body, cam))
            r_inf, r_rec, r_body = state.cache[name]
            pix, z = cam.project(P)
            H, W = r_inf.tri_id.shape
            inside = (z > 0) & (pix[:, 0] > -0.5) & (pix[:, 0] < W - 0.5) & (pix[:, 1] > -0.5) & (pix[:, 1] < H - 0.5)
            col = np.clip(np.rint(pix[:, 0]).astype(np.int64), 0, W - 1)
            row = np.clip(np.rint(pix[:, 1]).astype(np.int64), 0, H - 1)
            # Visible: no deeper than the farthest reconstructed surface in the 3x3 window.
            front = np.zeros(len(P))
            cand = []
            for dr in (-1, 0, 1):
                for dc in (-1, 0, 1):
                    rr, cc = np.clip(row + dr, 0, H - 1), np.clip(col + dc, 0, W - 1)
                    front = np.maximum(front, np.where(r_rec.tri_id[rr, cc] >= 0, r_rec.depth[rr, cc], 0.0))
                    cand.append(r_inf.tri_id[rr, cc])
            seen = inside & (z <= front * (1 + _VISIBILITY_TOLERANCE))
            if r_body is not None:  # and the body nearer than P at its pixel hides it
                body_depth = r_body.depth[row, col]
                seen &= ~((r_body.tri_id[row, col] >= 0) & (body_depth * (1 + _VISIBILITY_TOLERANCE) < z))
            cand = np.stack(cand, axis=1)
            ray = np.repeat(np.arange(len(P)), cand.shape[1])
            tri = cand.ravel()
            ok = (tri >= 0) & seen[ray]
            ray, tri = ray[ok], tri[ok]
            origin = cam.center
            t, b1, b2, _ = intersect_pairs(origin, P[ray] - origin, X_sub, sub_faces, tri)
            order = np.lexsort((t, ray))
            ray, tri, t, b1, b2 = ray[order], tri[order], t[order], b1[order], b2[order]
            first = np.r_[True, ray[1:] != ray[:-1]] if len(ray) else np.zeros(0, bool)
            good = first & np.isfinite(t)
            ray, tri, b1, b2 = ray[good], tri[good], b1[good], b2[good]
            T = tc.uv.astype(np.float64) + state.displacement[name]
            f = sub_faces[tri]
            uv = (1 - b1 - b2)[:, None] * T[f[:, 0]] + b1[:, None] * T[f[:, 1]] + b2[:, None] * T[f[:, 2]]
            same = chart_sub[f[:, 0]] == chart_sub[verts[ray]]
            ray, uv = ray[same], uv[same]
            total_w[ray] += w
            total_uv[ray] += w * uv
        got = total_w > 0
        d = np.array(d_blend, np.float64)
        d[verts[got]] = total_uv[got] / total_w[got, None] - tc.uv[verts[got]]
        a = np.array(a_blend)
        a[verts[got]] = True
        return d.astype(np.float32), a

    def _charts(self):
        if getattr(self, "_chart_cache", None) is None:

            base = uv_charts(self.dataset.faces, self.dataset.num_vertices)
            sub = charts_through_parent(base, self.texcoords.faces, len(self.texcoords.uv))
            self._chart_cache = (sub, base[np.asarray(self.dataset.faces)[:, 0]])
        return self._chart_cache
