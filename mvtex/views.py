"""Novel views between the cameras of an array (DESIGN §5 "Novel views", §7 `mvtex views`).

A novel view is given by weights w_p ≥ 0, Σ w_p = 1, over array cameras v_p:

    centre   c = Σ w_p c_p              (camera centres, world coordinates)
    K        K = Σ w_p K_p              (width and height must agree)
    R        weighted quaternion average of the R_p (SciPy `Rotation.mean`), slerp for two
             (SciPy `Slerp`; the same rotation as the average for two, in closed form)

A camera with weight 1 *is* that camera (returned unchanged but for its name).

Texture coordinates for the view, two methods:

- ``blend`` (the paper): T_N(v) = Σ w_p T_N(v_p), i.e. d(v) = Σ w_p d(v_p). A vertex is
  `assigned` where every camera with w_p > 0 assigned it (its d came from rays only).
- ``reconstruct`` (beyond the paper): triangulate the pose from the array cameras'
  texcoords (`mvtex.recon.reconstruct`), texture-slide the inferred mesh against that
  reconstruction from the novel camera itself (`mvtex.sliding.slide_pose`, the
  reconstruction standing in for the gt mesh), then combine (`ViewOptions.combine`):
  - "reproject" (default): the slide only says where the view's ray through a vertex meets
    the cloth (point P); the material there is read from the array cameras that see P
    (their own texcoords at P's projection), weighted by w_p. A depth error of P shifts
    its projection only by the baseline angle, so the reconstruction's error is damped.
  - "hit": the slid material itself where the hit triangle has three triangulated
    corners, the blend elsewhere.
  - "all": the slid material everywhere (plain sliding against the reconstruction).
  Where nothing better is known (no hit, no camera sees P) the blend is kept. Works from
  TS and TSNN texcoords alike: no gt is read. Measured on the built-in garment (stereo
  rig, midpoint, same-chart SqrtMSE): "reproject" beats the blend, "hit" ties with it,
  "all" loses to it (README, examples/views_path.py).

For both methods a view with weight 1 on one camera gets that camera's texcoords bit for
bit: the view is that camera, and its texcoords are the measured ones.
"""

from __future__ import annotations

import json
import os
import sys
import uuid
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from .camera import Camera, Rig, check_camera_name
from .errors import InputError
from .io import read_row
from .parallel import ThreadState

METHODS = ("blend", "reconstruct")
COMBINES = ("reproject", "hit", "all")
WEIGHT_TOLERANCE = 1e-6
# A point counts as seen by an array camera when it is no deeper than the farthest
# reconstructed surface around its projection, with this relative slack (4 mm at 2 m).
_VISIBILITY_TOLERANCE = 2e-3
_WRITE_BLOCK = 32  # poses computed between two writes of the output arrays


@dataclass(frozen=True)
class ViewOptions:
    """Options of `novel_views` (the `mvtex views` flags mirror them).

    Attributes:
        method: "blend" or "reconstruct" (see the module docstring).
        combine: for "reconstruct": "reproject", "hit" or "all" (module docstring).
        uv_resolution: texels per side of the UV lookup that finds the hit triangle.
    """

    method: str = "reconstruct"
    combine: str = "reproject"
    uv_resolution: int = 1024

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {', '.join(METHODS)}, got {self.method!r}")
        if self.combine not in COMBINES:
            raise ValueError(f"combine must be one of {', '.join(COMBINES)}, got {self.combine!r}")


# -- weights ---------------------------------------------------------------------------------

def parse_weights(text: str) -> dict[str, float]:
    """`"A=0.3,B=0.7"` -> {"A": 0.3, "B": 0.7}; InputError on malformed text."""
    weights: dict[str, float] = {}
    for item in str(text).split(","):
        item = item.strip()
        if not item:
            continue
        name, sep, value = item.partition("=")
        name = name.strip()
        try:
            w = float(value) if sep else float("nan")
        except ValueError:
            w = float("nan")
        if not name or not sep or not np.isfinite(w):
            raise InputError(None, f"--weights: {item!r} is not NAME=NUMBER (e.g. \"left=0.5,right=0.5\")")
        if name in weights:
            raise InputError(None, f"--weights: camera {name!r} given twice")
        weights[name] = w
    if not weights:
        raise InputError(None, "--weights: no camera given")
    return weights


def check_weights(weights: Mapping[str, float], rig: Rig, source: str | os.PathLike | None = None) -> dict[str, float]:
    """Weights of a view, validated: known cameras, finite, ≥ 0, summing to 1 (±1e-6)."""
    rig.select(list(weights), source)  # InputError naming unknown cameras
    values = np.array([float(w) for w in weights.values()], np.float64)
    if not np.all(np.isfinite(values)):
        raise InputError(None, f"weights must be finite numbers, got {dict(weights)}")
    if np.any(values < 0):
        raise InputError(None, f"weights must be >= 0, got {dict(weights)}")
    if abs(values.sum() - 1.0) > WEIGHT_TOLERANCE:
        raise InputError(None, f"weights must sum to 1 (within {WEIGHT_TOLERANCE:g}), they sum to {values.sum():.9g}")
    return {str(k): float(v) for k, v in weights.items()}


def between_weights(a: str, b: str, steps: int) -> list[dict[str, float]]:
    """`steps` views evenly along the segment a -> b, both ends included (t = i/(steps-1))."""
    if int(steps) < 2:
        raise InputError(None, f"--steps must be at least 2, got {steps}")
    if a == b:
        raise InputError(None, f"--between needs two different cameras, got {a},{b}")
    out = []
    for i in range(int(steps)):
        t = i / (int(steps) - 1)
        out.append({a: 1.0 - t, b: t})
    return out


def grid_weights(a: str, b: str, c: str, d: str, steps: int) -> list[dict[str, float]]:
    """steps × steps views bilinear over a 2×2 array, row-major from `a`.

    Corners: a at (row 0, column 0), b at (row 0, last column), c at (last row, column 0),
    d at (last row, last column); view (i, j) has s = j/(steps-1) along a->b and
    t = i/(steps-1) along a->c.
    """
    if int(steps) < 2:
        raise InputError(None, f"--steps must be at least 2, got {steps}")
    if len({a, b, c, d}) != 4:
        raise InputError(None, f"--grid needs four different cameras, got {a},{b},{c},{d}")
    out = []
    n = int(steps)
    for i in range(n):
        t = i / (n - 1)
        for j in range(n):
            s = j / (n - 1)
            out.append({a: (1 - s) * (1 - t), b: s * (1 - t), c: (1 - s) * t, d: s * t})
    return out


def view_names(count: int) -> list[str]:
    """view_000, view_001, ..."""
    return [f"view_{i:03d}" for i in range(count)]


# -- cameras -----------------------------------------------------------------------------------

def _single(weights: Mapping[str, float]) -> str | None:
    """The camera with weight exactly 1 (all others 0), if any."""
    ones = [k for k, w in weights.items() if w == 1.0]
    if len(ones) == 1 and all(w == 0.0 for k, w in weights.items() if k != ones[0]):
        return ones[0]
    return None


def interpolate_camera(rig: Rig, weights: Mapping[str, float], name: str) -> Camera:
    """The novel camera of `weights` over cameras of `rig` (see the module docstring).

    Args:
        rig: the array; weights: camera name -> weight (validated with `check_weights`).
        name: the new camera's name.

    Returns:
        Camera: width/height of the array cameras, K and centre blended, R averaged.

    Raises:
        InputError: the cameras' image sizes differ, or the weights are invalid.
    """
    from scipy.spatial.transform import Rotation, Slerp

    weights = check_weights(weights, rig)
    one = _single(weights)
    if one is not None:
        return rig[one].with_name(name)
    used = [(rig[k], w) for k, w in weights.items() if w > 0]
    sizes = {(c.width, c.height) for c, _ in used}
    if len(sizes) > 1:
        raise InputError(None, "cameras " + ", ".join(c.name for c, _ in used) +
                         f" have different image sizes {sorted(sizes)}: a view can only blend cameras of one size")
    w = np.array([x for _, x in used], np.float64)
    w = w / w.sum()
    cams = [c for c, _ in used]
    centre = np.einsum("p,pi->i", w, np.stack([c.center for c in cams]))
    K = np.einsum("p,pij->ij", w, np.stack([c.K for c in cams]))
    dist = np.einsum("p,pi->i", w, np.stack([c.dist for c in cams]))
    rotations = Rotation.from_matrix(np.stack([c.R for c in cams]))
    if len(cams) == 2:
        R = Slerp([0.0, 1.0], rotations)([w[1]]).as_matrix()[0]
    else:
        R = rotations.mean(weights=w).as_matrix()
    return Camera(name=name, width=cams[0].width, height=cams[0].height, K=K, R=R, t=-R @ centre, dist=dist)


def weights_for_centre(rig: Rig, names: Sequence[str], centre: np.ndarray) -> dict[str, float]:
    """Weights ≥ 0 summing to 1 over cameras `names` whose blended centre is nearest `centre`
    (non-negative least squares with the sum as a heavily weighted extra row)."""
    from scipy.optimize import nnls

    C = np.stack([rig[n].center for n in names], axis=1)  # (3,p)
    scale = 1e3 * max(1.0, float(np.abs(C).max()))
    A = np.vstack([C, np.full((1, len(names)), scale)])
    b = np.concatenate([np.asarray(centre, np.float64), [scale]])
    w, _ = nnls(A, b)
    w = w / w.sum()
    return {n: float(x) for n, x in zip(names, w)}


# -- texcoords -----------------------------------------------------------------------------------

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
        reconstruction: `mvtex.recon.Reconstruction` or None (method "blend").
        cache: per array camera, its rasters of the inferred and reconstructed meshes.
    """

    pose: int
    displacement: dict[str, np.ndarray]
    assigned: dict[str, np.ndarray]
    inferred: np.ndarray
    reconstruction: object | None = None
    cache: dict | None = None


class ViewSynthesizer:
    """Texcoords of novel views for the poses of one texcoord set.

    Args:
        dataset: a `Dataset` (only its mesh, inferred positions and rest shape are read).
        rig: the array's rig (must hold the texcoord set's cameras).
        texcoords: a `TexcoordSet` of the array.
        options: ViewOptions.
        rig_source: the rig's path, for error messages.
    """

    def __init__(self, dataset, rig: Rig, texcoords, options: ViewOptions = ViewOptions(),
                 rig_source: str | os.PathLike | None = None, ctx=None):
        check_texcoords_rig(texcoords, rig, rig_source)
        if texcoords.num_base_vertices != dataset.num_vertices:
            raise InputError(texcoords.path / "mesh.npz", f"made for a mesh of {texcoords.num_base_vertices} "
                             f"vertices, the dataset has {dataset.num_vertices}")
        from .raster import GLContext

        self.dataset = dataset
        self._owns_gl = ctx is None
        self.gl = GLContext() if ctx is None else ctx
        self.rig = rig
        self.texcoords = texcoords
        self.options = options
        self.array = [c for c in texcoords.cameras if c in rig.names]
        self._topology = None
        self._slide_options = None
        from .recon import ReconOptions

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
            from .sliding import SlideOptions, build_topology

            tc = self.texcoords
            recorded = tc.meta.get("options") if isinstance(tc.meta.get("options"), dict) else {}
            known = {k: v for k, v in recorded.items() if k in SlideOptions.__dataclass_fields__}
            known["subdiv"] = tc.subdiv
            self._slide_options = SlideOptions(**known)
            ds = self.dataset
            from .dataset import reference_shape

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
                          inferred=read_row(self.dataset.inferred, pose).astype(np.float64))
        if self.options.method == "reconstruct":
            from .recon import reconstruct

            if len(self.array) < 2:
                raise InputError(tc.path, "method reconstruct needs texcoords of at least 2 rig cameras "
                                 f"(the set has {', '.join(tc.cameras)})")
            X_N = tc.positions(state.inferred)
            T = {c: tc.uv.astype(np.float64) + state.displacement[c] for c in self.array}
            state.reconstruction = reconstruct(self.dataset.uv, X_N, tc.faces, tc.uv, T, self.rig.select(self.array),
                                             self.recon_options, gt_faces=self.dataset.faces, assigned=state.assigned,
                                             progress=progress, ctx=self.gl)
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
        from .sliding import slide_pose

        topo, slide_options = self._sliding()
        rec = state.reconstruction
        d_rec, a_rec = slide_pose(rec.points, state.inferred, self.dataset.faces, self.dataset.uv, camera,
                                  topo.subdivision, slide_options, topology=topo, ctx=self.gl)
        if self.options.combine == "all":
            return d_rec, a_rec
        if self.options.combine == "reproject":
            return self._reproject(state, camera, weights, d_rec, a_rec, d_blend, a_blend)
        trusted = self._trusted(d_rec, a_rec, rec.triangulated)
        d = np.where(trusted[:, None], d_rec, d_blend).astype(np.float32)
        return d, np.where(trusted, a_rec, a_blend)

    def _hit_points(self, d_rec: np.ndarray, a_rec: np.ndarray, points: np.ndarray):
        """Where the slide against the reconstruction hit it, found from the slid uv (the
        reconstruction carries T_G): (k,) vertex indices, (k,3) hit points P, (k,) hit face
        of the base mesh."""
        from .locate import locate_uv

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
        from .raster import rasterize
        from .sliding import intersect_pairs

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
                                    rasterize(self.gl, rec.points, self.dataset.faces, cam))
            r_inf, r_rec = state.cache[name]
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
            from .mesh import charts_through_parent, uv_charts

            base = uv_charts(self.dataset.faces, self.dataset.num_vertices)
            sub = charts_through_parent(base, self.texcoords.faces, len(self.texcoords.uv))
            self._chart_cache = (sub, base[np.asarray(self.dataset.faces)[:, 0]])
        return self._chart_cache

    def _trusted(self, d_rec: np.ndarray, a_rec: np.ndarray, triangulated: np.ndarray) -> np.ndarray:
        """(n',) bool: where the slide against the reconstruction is believed."""
        tc = self.texcoords
        faces = np.asarray(self.dataset.faces, np.int64)
        from .locate import locate_uv

        hit_uv = tc.uv.astype(np.float64) + d_rec
        idx = np.flatnonzero(a_rec)
        point, face, _ = locate_uv(hit_uv[idx], faces, self.dataset.uv, self.options.uv_resolution, ctx=self.gl)
        good = np.all(triangulated[faces[face]], axis=1)
        # A point on a shared edge lies in several triangles: all must be good.
        bad_points = np.unique(point[~good])
        ok_points = np.setdiff1d(np.unique(point), bad_points)
        trusted = np.zeros(len(a_rec), bool)
        trusted[idx[ok_points]] = True
        return trusted


def check_texcoords_rig(texcoords, rig: Rig, rig_source: str | os.PathLike | None = None) -> None:
    """InputError unless the texcoord set's cameras are in the rig (and, where the set
    records the cameras it was made with, are the same cameras)."""
    missing = [c for c in texcoords.cameras if c not in rig.names]
    if missing:
        raise InputError(texcoords.path, f"cameras {', '.join(missing)} of this texcoord set are not in the rig "
                         f"{rig_source or ''} (it has {', '.join(rig.names)}): a texcoord set from another rig?")
    recorded = texcoords.meta.get("rig")
    if isinstance(recorded, dict):
        for name, rec in recorded.items():
            if name not in rig.names or not isinstance(rec, dict):
                continue
            cam = rig[name]
            try:
                same = (int(rec["width"]) == cam.width and int(rec["height"]) == cam.height and
                        np.allclose(rec["K"], cam.K, atol=1e-6) and np.allclose(rec["R"], cam.R, atol=1e-6) and
                        np.allclose(rec["t"], cam.t, atol=1e-6))
            except (KeyError, TypeError, ValueError):
                continue
            if not same:
                raise InputError(texcoords.path, f"camera {name!r} of this texcoord set was made with other "
                                 f"parameters than the rig's {rig_source or ''} camera of that name")


# -- the command ------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _ViewSpec:
    """What a worker needs to compute views (picklable): paths, not open files."""

    dataset: str
    rig: Rig
    texcoords: str
    options: ViewOptions
    rig_source: str | None
    cameras: tuple
    weights: tuple
    key: str  # one run: a worker keeps its synthesizer between the run's tasks


_VIEW_STATE = ThreadState()  # each thread's synthesizer for the run it serves


def _view_state(spec: _ViewSpec) -> "ViewSynthesizer":
    """A worker's synthesizer for a run."""
    from .dataset import load_dataset
    from .slide_jobs import single_thread_gl
    from .texcoords import open_texcoords

    single_thread_gl()
    ds = load_dataset(spec.dataset, validate=False)
    return ViewSynthesizer(ds, spec.rig, open_texcoords(spec.texcoords, ds.num_vertices), spec.options,
                           spec.rig_source)


def _views_of_poses(synth: "ViewSynthesizer", cameras: Sequence[Camera], weights: Sequence[Mapping[str, float]],
                    poses: Sequence[int]) -> tuple[dict, dict]:
    """Every view of `poses`: ({name: (p,n',2) float32}, {name: (p,n') bool})."""
    n_sub = len(synth.texcoords.uv)
    disp = {c.name: np.empty((len(poses), n_sub, 2), np.float32) for c in cameras}
    asg = {c.name: np.empty((len(poses), n_sub), bool) for c in cameras}
    for row, pose in enumerate(poses):
        state = synth.prepare(pose)
        for cam, w in zip(cameras, weights):
            disp[cam.name][row], asg[cam.name][row] = synth.view(state, cam, w)
    return disp, asg


def _view_block(spec: _ViewSpec, start: int, poses: list[int]):
    """In a worker: the views of one block of poses; returns (start, disp, asg)."""
    synth = _VIEW_STATE.get(spec.key, lambda: _view_state(spec))
    return (start, *_views_of_poses(synth, spec.cameras, spec.weights, poses))


def novel_views(dataset, rig: Rig, texcoords, out: str | os.PathLike, weights: Sequence[Mapping[str, float]],
                names: Sequence[str], *, poses: Sequence[int] | None = None, options: ViewOptions = ViewOptions(),
                rig_source: str | os.PathLike | None = None, progress: bool = True, workers: int = 1,
                scheduler: str | None = None) -> dict:
    """`mvtex views`: a texcoord set whose cameras are novel views of an array.

    Args:
        dataset: `Dataset`. rig: the array's `Rig`. texcoords: the array's `TexcoordSet`.
        out: the directory to write: a texcoord set (DESIGN §4) with source
            "views-<method>" and `rig.yaml` holding the novel cameras. It is built in
            ``OUT.partial`` beside it, block by block of poses with a done mask, and renamed
            into place when complete; a rerun with the same inputs (content fingerprints)
            and settings continues where an interrupted run stopped.
        weights: one weight map per view (array camera -> weight). names: the views' names.
        poses: dataset pose indices (default: the set's poses).
        options: ViewOptions.
        workers: local worker processes (1: this process), see `mvtex.parallel.map_unordered`.
        scheduler: Dask scheduler address (overrides `workers`). Workers compute blocks of
            `_WRITE_BLOCK` poses; the result does not depend on where they ran.

    Returns:
        {"out", "method", "views": {name: weights}, "poses": [...], "cameras": {name: centre}}.
    """
    from tqdm import tqdm

    from .camera import save_rig
    from .io import dumps_strict, fingerprint, load_npy, remove_leftovers, replace_path, save_npy, write_npy_rows
    from .texcoords import open_unfinished

    if len(weights) != len(names) or not names:
        raise ValueError("one name per view is needed")
    if len(set(names)) != len(names):
        raise InputError(None, f"view names must be unique, got {list(names)}")
    for name in names:  # they become folder names
        try:
            check_camera_name(name)
        except ValueError as err:
            raise InputError(None, str(err)) from None
    weights = [check_weights(w, rig, rig_source) for w in weights]
    synth = ViewSynthesizer(dataset, rig, texcoords, options, rig_source)
    for w in weights:
        absent = [c for c in w if c not in texcoords.cameras]
        if absent:
            raise InputError(texcoords.path, f"no texcoords for camera {', '.join(absent)} in this set "
                             f"(it has {', '.join(texcoords.cameras)})")
    cameras = [interpolate_camera(rig, w, name) for w, name in zip(weights, names)]
    poses = texcoords.poses if poses is None else [int(p) for p in poses]
    for p in poses:
        texcoords.row(p)
    if poses:  # reading a row checks the camera's whole arrays: here, before any worker starts
        for c in synth.array:
            texcoords.displacement(c, poses[0])
    out = Path(out)
    record = {"views": {name: dict(w) for name, w in zip(names, weights)}, "method": options.method,
              "view_options": asdict(options), "from": {"texcoords": str(Path(texcoords.path).resolve()),
                                                        "source": texcoords.source, "cameras": texcoords.cameras},
              # Content, not only paths: a rerun continues only from the same inputs.
              "inputs": {"dataset": fingerprint(dataset.inferred, dataset.poses, dataset.faces, dataset.uv),
                         "texcoords": {c: texcoords.fingerprint(c) for c in synth.array},
                         "rig": {c.name: [c.width, c.height, c.K.tolist(), c.R.tolist(), c.t.tolist()] for c in rig}}}
    record = json.loads(dumps_strict(record))  # as texcoords.json holds it (lists, not tuples)
    partial = out.with_name(out.name + ".partial")
    with synth:
        open_unfinished(partial, "views", "views-", faces=texcoords.faces, uv=texcoords.uv,
                        parent=texcoords.parent, source=f"views-{options.method}", subdiv=texcoords.subdiv,
                        poses=poses, cameras=list(names), done_masks=["done.npy"], **record)
        # A run killed while saving the done mask leaves its hidden temporary and aside
        # copies; without the mask every block is computed again.
        remove_leftovers(partial, "done.npy")
        done = np.zeros(len(poses), bool)
        if (partial / "done.npy").is_file():
            done = np.array(load_npy(partial / "done.npy", mmap=False), dtype=bool)

        def write(start: int, disp: dict, asg: dict) -> None:
            # Through the files, not maps: pages written through a map stay in the process's
            # resident memory while it is open, which would grow with the run. The rows are
            # on disk before the done mask says so.
            count = len(next(iter(asg.values())))
            for name in names:
                for file, values in (("displacement.npy", disp[name]), ("assigned.npy", asg[name])):
                    write_npy_rows(partial / name / file, range(start, start + count), values)
            done[start:start + count] = True
            save_npy(partial / "done.npy", done)
            bar.update(count * len(names))

        size = _WRITE_BLOCK
        if workers > 1 or scheduler:  # blocks small enough that every worker gets several
            size = max(1, min(_WRITE_BLOCK, -(-len(poses) // (4 * max(workers, 2)))))
        starts = [start for start in range(0, len(poses), size) if not done[start:start + size].all()]
        bar = tqdm(total=len(poses) * len(names), initial=int(done.sum()) * len(names),
                   desc=f"views ({options.method})", unit="view", disable=not progress, file=sys.stderr)
        if workers <= 1 and not scheduler:
            for start in starts:
                write(start, *_views_of_poses(synth, cameras, weights, poses[start:start + size]))
        else:
            from .parallel import map_unordered

            spec = _ViewSpec(dataset=str(Path(dataset.path).resolve()), rig=rig,
                             texcoords=str(Path(texcoords.path).resolve()), options=options,
                             rig_source=None if rig_source is None else str(rig_source), cameras=tuple(cameras),
                             weights=tuple(dict(w) for w in weights), key=uuid.uuid4().hex)
            tasks = [(spec, start, poses[start:start + size]) for start in starts]
            for start, disp, asg in map_unordered(_view_block, tasks, workers=workers, scheduler=scheduler):
                write(start, disp, asg)
        bar.close()
    save_rig(Rig(tuple(cameras)), partial / "rig.yaml")
    # Rename the finished set in (an older `out` aside first), then drop the done mask: a
    # stop in between leaves either a resumable partial or a complete set.
    replace_path(partial, out)
    (out / "done.npy").unlink(missing_ok=True)
    return {"out": str(out), "method": options.method, "views": record["views"], "poses": poses,
            "cameras": {c.name: c.center.tolist() for c in cameras}}
