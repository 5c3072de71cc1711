"""Per-pixel texture-coordinate error (DESIGN §5 "Per-pixel error", the paper's SqrtMSE).

The ground-truth mesh is rendered with its uv (T_G) and the inferred mesh with the
texcoords under test from the same camera; over the pixels covered by both,
e = ‖uv_inferred − uv_gt‖ and an image's SqrtMSE = sqrt(mean e²). `evaluate` reports the
mean ± std over images for the baseline (inferred mesh with T_G) and for a texcoord set.

Where the two meshes show different UV charts at a pixel (a side seam near the silhouette,
the rim of an opening), e measures the distance between charts in the atlas, not between
material points: a handful of such pixels (e ≈ 0.5–1) can outweigh everything else. No
texcoords can remove them, since the charts' boundaries are fixed by each mesh's geometry.
`evaluate` therefore also reports `sqrt_mse_same_chart`: the same statistic over the pixels
where both meshes show the same chart (the contract keys are unchanged).

The *material error* needs no such exclusion: at a pixel, each mesh shows a point of the
garment's material — for gt the barycentric combination of the rest positions (mesh.npz
`rest`) of the triangle it shows, for the inferred mesh the point its texcoords name in the
uv layout, mapped back to the rest shape (`MaterialMap`). Their distance on the rest
garment, in meters, is small across a seam (both sides of it are neighbours on the
cloth). `evaluate` reports its RMSE per image as `material_rmse_m` (null without `rest`).

Texture sliding cannot name the material where no ray assigned it (the paper's occluded
vertices, filled smoothly). `material_rmse_assigned_m` is the material error over the
pixels of the set's triangles whose three corners are all assigned (`assigned.npy`), and
`assigned_share` the share of the compared pixels that is; the baseline is measured over
the same pixels. For a set assigned everywhere (a model's prediction) both errors are one.

On a corrected set (`mvtex correct`: its inferred mesh is the geometry corrector's) the
baseline is the corrected mesh with T_G, and `original_inferred` also reports the mesh
before the correction with T_G (the set keeps it), so a ratio can be read against either.
"""

from __future__ import annotations

import contextlib
import os
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from tqdm import tqdm

from mvtex.data.dataset import as_dataset, load_dataset
from mvtex.data.mesh import apply_extension, charts_through_parent, extension_matrix, subdivide, uv_charts
from mvtex.data.rig import Rig, as_rig, check_outside_body, check_sees
from mvtex.data.texcoords import TexcoordSet, open_texcoords
from mvtex.evaluation.kernels import pixel_errors
from mvtex.evaluation.material import MaterialMap
from mvtex.evaluation.uv import CHART_BOUNDARY_COLOR
from mvtex.render.context import GLContext
from mvtex.render.pictures import BACKGROUND, ColorScale, caption, colorbar, heatmap, legend, side_by_side, stack
from mvtex.render.raster import PairRaster, rasterize, rasterize_pair_attributes
from mvtex.render.shading import BODY_RGB
from mvtex.util.checks import as_indices, as_path
from mvtex.util.errors import OptionError
from mvtex.util.files import read_row, save_png
from mvtex.util.output import atomic_path, writer
from mvtex.util.parallel import ThreadState, WorkerState, check_backend, configure_threads, map_unordered


@dataclass(frozen=True)
class Stats:
    """Mean and standard deviation of a per-image error over images (NaN when none counts)."""

    mean: float
    std: float

    @classmethod
    def of(cls, values: Sequence[float]) -> "Stats":
        v = np.asarray([x for x in values if np.isfinite(x)], dtype=np.float64)
        return cls(float("nan"), float("nan")) if v.size == 0 else cls(float(v.mean()), float(v.std()))


@dataclass(frozen=True)
class Comparison:
    """One error of the baseline (the inferred mesh with T_G, "inferred") and of a texcoord
    set ("texcoords") over the same images."""

    inferred: Stats
    texcoords: Stats

    @property
    def ratio(self) -> float:
        """inferred mean / texcoords mean: how many times smaller the texcoords' error is (NaN
        when undefined)."""
        t = self.texcoords.mean
        return self.inferred.mean / t if np.isfinite(t) and t > 0 else float("nan")

    def to_json(self) -> dict:
        return {"inferred": asdict(self.inferred), "texcoords": asdict(self.texcoords)}


@dataclass(frozen=True)
class Evaluation:
    """What `evaluate` measures (DESIGN §7 `mvtex eval`).

    Attributes:
        num_images: images where both meshes cover a pixel (the others are skipped).
        sqrt_mse: the per-pixel uv error (DESIGN §5), SqrtMSE per image.
        sqrt_mse_same_chart: the same over the pixels where both meshes show one UV chart.
        material_rmse_m: the material error in meters, RMSE per image; None for a dataset
            without a rest shape.
        body_share: of the pixels where either render shows cloth, the share where the
            other shows the body (left out of both errors), per image; None for a dataset
            without a body.
        material_rmse_assigned_m: the material error over the pixels of fully assigned
            triangles (all three corners assigned in the set); None without a rest shape.
        assigned_share: of the compared pixels, the share on fully assigned triangles, per
            image.
        per_camera: camera name -> the same for its images (no `per_camera` of its own).
        original_inferred: on a corrected set, the errors of the mesh before the correction
            with T_G over the same images: {"sqrt_mse", "material_rmse_m" (None without a
            rest shape)} as `Stats`; None on any other dataset.
    """

    num_images: int
    sqrt_mse: Comparison
    sqrt_mse_same_chart: Comparison
    material_rmse_m: Comparison | None
    body_share: Stats | None = None
    material_rmse_assigned_m: Comparison | None = None
    assigned_share: Stats | None = None
    per_camera: dict[str, "Evaluation"] = field(default_factory=dict)
    original_inferred: dict[str, Stats | None] | None = None

    @property
    def ratio_original(self) -> float | None:
        """On a corrected set: the original mesh's uv error over the texcoords' (else None)."""
        if self.original_inferred is None:
            return None
        return Comparison(self.original_inferred["sqrt_mse"], self.sqrt_mse.texcoords).ratio

    @property
    def ratio_material_original(self) -> float | None:
        """On a corrected set with a rest shape: the original mesh's material error over the
        texcoords' (else None)."""
        if self.original_inferred is None or self.original_inferred["material_rmse_m"] is None:
            return None
        return Comparison(self.original_inferred["material_rmse_m"], self.material_rmse_m.texcoords).ratio

    @property
    def ratio(self) -> float:
        return self.sqrt_mse.ratio

    @property
    def ratio_same_chart(self) -> float:
        return self.sqrt_mse_same_chart.ratio

    @property
    def ratio_material(self) -> float | None:
        return None if self.material_rmse_m is None else self.material_rmse_m.ratio

    @property
    def ratio_material_assigned(self) -> float | None:
        return None if self.material_rmse_assigned_m is None else self.material_rmse_assigned_m.ratio

    def to_json(self) -> dict:
        """The JSON object of `mvtex eval --json`."""
        out = {"num_images": self.num_images,
               "sqrt_mse": self.sqrt_mse.to_json(), "ratio": self.ratio,
               "sqrt_mse_same_chart": self.sqrt_mse_same_chart.to_json(), "ratio_same_chart": self.ratio_same_chart,
               "material_rmse_m": None if self.material_rmse_m is None else self.material_rmse_m.to_json(),
               "ratio_material": self.ratio_material,
               "material_rmse_assigned_m": (None if self.material_rmse_assigned_m is None
                                            else self.material_rmse_assigned_m.to_json()),
               "ratio_material_assigned": self.ratio_material_assigned,
               "assigned_share": None if self.assigned_share is None else asdict(self.assigned_share),
               "body_share": None if self.body_share is None else asdict(self.body_share)}
        if self.original_inferred is not None:
            m = self.original_inferred["material_rmse_m"]
            out["original_inferred"] = {"sqrt_mse": asdict(self.original_inferred["sqrt_mse"]),
                                        "material_rmse_m": None if m is None else asdict(m),
                                        "ratio": self.ratio_original, "ratio_material": self.ratio_material_original}
        if self.per_camera:
            out["per_camera"] = {name: e.to_json() for name, e in self.per_camera.items()}
        return out


def _summary(images: list[tuple], has_rest: bool, has_body: bool,
             per_camera: dict[str, Evaluation] | None = None, has_original: bool = False) -> Evaluation:
    """Per-image values (`ImageErrors.values`, then on a corrected set the original mesh's
    uv and material errors; NaN where an image does not count) -> an `Evaluation` over the
    images where both the baseline and the texcoords have an error."""
    ok = [v for v in images if np.isfinite(v[0]) and np.isfinite(v[1])]

    def compare(i):
        return Comparison(Stats.of([v[i] for v in ok]), Stats.of([v[i + 1] for v in ok]))

    original = None
    if has_original:
        original = {"sqrt_mse": Stats.of([v[10] for v in ok]),
                    "material_rmse_m": Stats.of([v[11] for v in ok]) if has_rest else None}
    return Evaluation(num_images=len(ok), sqrt_mse=compare(0), sqrt_mse_same_chart=compare(2),
                      material_rmse_m=compare(4) if has_rest else None,
                      body_share=Stats.of([v[6] for v in ok]) if has_body else None,
                      material_rmse_assigned_m=compare(7) if has_rest else None,
                      assigned_share=Stats.of([v[9] for v in ok]), per_camera=per_camera or {},
                      original_inferred=original)


@dataclass(frozen=True)
class _EvalSpec:
    """What a worker needs to evaluate images: picklable; its opened inputs are kept per thread by key."""

    dataset: str
    texcoords: str
    rig: Rig
    heatmaps: str | None
    original: bool = False  # a corrected set: also the mesh before the correction with T_G

    @property
    def key(self) -> tuple[str, str]:
        return self.dataset, self.texcoords


@dataclass
class ImageErrors:
    """The errors of one image (`ImageEvaluator`): per-image statistics (NaN where no pixel
    counts) and, for the heatmaps, per-pixel values at `pixels` (flat indices into the box
    of `raster`) where both renders show cloth.

    Attributes:
        sqrt_mse, sqrt_mse_same_chart: (baseline, texcoords) uv SqrtMSE, over all pixels
            and over the pixels where both show one chart.
        material_rmse_m: (baseline, texcoords) material RMSE in meters (NaN without rest).
        body_share: of the pixels where either render shows cloth, the share where the other
            shows the body (NaN without a body).
        material_rmse_assigned_m: (baseline, texcoords) material RMSE over the pixels of
            fully assigned triangles (NaN without rest or without such pixels).
        assigned_share: the share of `pixels` on fully assigned triangles.
        pixels, e_b, e_t, other_chart, mat_b, mat_t: per-pixel values; in_assigned: pixels on
            fully assigned triangles; body_pixels: where either render shows the body.
            raster: the `PairRaster` they were read from.
    """

    sqrt_mse: tuple[float, float]
    sqrt_mse_same_chart: tuple[float, float]
    material_rmse_m: tuple[float, float]
    body_share: float
    material_rmse_assigned_m: tuple[float, float]
    assigned_share: float
    in_assigned: np.ndarray
    pixels: np.ndarray
    e_b: np.ndarray
    e_t: np.ndarray
    other_chart: np.ndarray
    mat_b: np.ndarray | None
    mat_t: np.ndarray | None
    body_pixels: np.ndarray
    raster: Any

    def values(self) -> tuple[float, ...]:
        """(s_b, s_t, same_b, same_t, m_b, m_t, body_share, assigned m_b, assigned m_t, assigned_share)."""
        return (*self.sqrt_mse, *self.sqrt_mse_same_chart, *self.material_rmse_m, self.body_share,
                *self.material_rmse_assigned_m, self.assigned_share)


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e * e))) if e.size else float("nan")


class ImageEvaluator:
    """Both errors of single images (DESIGN §5) of a dataset: the gt cloth with T_G against
    the inferred mesh with T_G (the baseline) and against the inferred mesh of a texcoord
    set's topology with given texcoords, the body (if any) in every render.

    Args:
        ctx: the GL context.
        dataset: a `Dataset`.
        faces, uv, parent: the texcoord set's mesh (`mesh.npz`: faces, T_G, parent).

    When `faces` are the dataset's `mesh.subdivide`d (every mesh mvtex writes), one pair
    raster gives all three renders: the base inferred mesh with T_G is the same surface as
    the subdivided one, read through the same pixels. Otherwise gt and the set's mesh are
    rasterized separately.
    """

    def __init__(self, ctx: GLContext, dataset, faces: np.ndarray, uv: np.ndarray, parent: np.ndarray):

        self.ctx, self.dataset = ctx, dataset
        self.faces = np.ascontiguousarray(dataset.faces, np.int64)
        self.sub_faces = np.ascontiguousarray(faces, np.int64)
        self.sub_uv = np.ascontiguousarray(uv, np.float32)
        self._extend = extension_matrix(np.asarray(parent))
        self.levels = int(round(np.log(max(len(faces), 1) / max(len(self.faces), 1)) / np.log(4)))
        self.pair = bool(np.array_equal(subdivide(self.faces, dataset.num_vertices, self.levels).faces, self.sub_faces))
        charts = uv_charts(self.faces, dataset.num_vertices)
        self.face_chart = charts[self.faces[:, 0]]
        self.sub_face_chart = charts_through_parent(charts, self.sub_faces, len(uv))[self.sub_faces[:, 0]]
        has_rest = dataset.rest is not None
        self.material_map = MaterialMap(dataset.faces, dataset.uv, dataset.rest, ctx=ctx) if has_rest else None
        self.rest = np.ascontiguousarray(dataset.rest, np.float64) if has_rest else np.zeros((0, 3))
        self.rest_sub = self.positions(self.rest) if has_rest else np.zeros((0, 3))

    def positions(self, base: np.ndarray) -> np.ndarray:
        """Base positions (n,3) on the set's mesh, (n',3) float64."""

        return np.asarray(apply_extension(self._extend, np.asarray(base, np.float64)), np.float64)

    def _renders(self, gt: np.ndarray, inferred: np.ndarray, cam, body):

        if self.pair:
            pixels = np.concatenate([cam.project(gt)[0], cam.project(inferred)[0]])
            return rasterize_pair_attributes(self.ctx, gt, inferred, self.faces, cam, levels=self.levels,
                                             pixels=pixels, occluder=body)
        r_g = rasterize(self.ctx, gt, self.faces, cam, occluder=body)
        r_t = rasterize(self.ctx, self.positions(inferred), self.sub_faces, cam, occluder=body)
        m, ms = len(self.faces), len(self.sub_faces)
        base_tri = r_g.tri_id if body is None else np.where(r_g.body, m, r_g.tri_id)
        sub_tri = r_t.tri_id if body is None else np.where(r_t.body, ms, r_t.tri_id)
        return PairRaster(box=(0, cam.height, 0, cam.width), base_tri=base_tri, sub_tri=sub_tri,
                          base_bary=r_g.bary, sub_bary=r_t.bary)

    def __call__(self, pose: int, cam, texcoords: np.ndarray, *, assigned: np.ndarray | None = None,
                 gt: np.ndarray | None = None, inferred: np.ndarray | None = None) -> ImageErrors:
        """The errors of pose `pose` from camera `cam` with `texcoords` (n',2) on the set's
        mesh, over the pixels where both renders show cloth. assigned: (n',) bool, the set's
        assigned vertices for this image (None: all). gt, inferred: the pose's base
        positions when already read (else read through the files)."""

        ds = self.dataset
        # Through the files (`read_row`): rows read through the dataset's maps stay resident.
        gt = read_row(ds.gt, pose).astype(np.float64) if gt is None else np.asarray(gt, np.float64)
        inferred = read_row(ds.inferred, pose).astype(np.float64) if inferred is None else np.asarray(inferred,
                                                                                                      np.float64)
        body = None if ds.body is None else (ds.body.pose(pose), ds.body.faces)
        raster = self._renders(gt, inferred, cam, body)
        m, ms = len(self.faces), len(self.sub_faces)
        base_tri, sub_tri = raster.base_tri.ravel(), raster.sub_tri.ravel()
        pixels, e_b, e_t, uv_t, other, points_g, mat_b, hidden, covered = pixel_errors(
            base_tri, raster.base_bary.reshape(-1, 3), sub_tri, raster.sub_bary.reshape(-1, 3), m, ms, self.faces,
            ds.uv, self.rest, self.sub_faces, self.sub_uv, self.rest_sub, np.ascontiguousarray(texcoords, np.float32),
            self.face_chart, self.sub_face_chart)
        body_share = float("nan") if body is None or not covered else hidden / covered
        body_pixels = np.flatnonzero((base_tri >= m) | (sub_tri >= ms)) if body is not None else np.zeros(0, np.int64)
        if assigned is None:
            in_assigned = np.ones(len(pixels), bool)
        else:
            in_assigned = np.asarray(assigned, bool)[self.sub_faces[sub_tri[pixels]]].all(axis=1)
        mat_t = None
        materials = assigned_materials = (float("nan"), float("nan"))
        if self.material_map is not None:
            mat_t = np.linalg.norm(self.material_map(uv_t) - points_g, axis=1)
            materials = (_rms(mat_b), _rms(mat_t))
            assigned_materials = (_rms(mat_b[in_assigned]), _rms(mat_t[in_assigned]))
        else:
            mat_b = None
        share = float(in_assigned.mean()) if len(pixels) else float("nan")
        return ImageErrors(sqrt_mse=(_rms(e_b), _rms(e_t)), sqrt_mse_same_chart=(_rms(e_b[~other]), _rms(e_t[~other])),
                           material_rmse_m=materials, body_share=body_share,
                           material_rmse_assigned_m=assigned_materials, assigned_share=share, in_assigned=in_assigned,
                           pixels=pixels, e_b=e_b, e_t=e_t, other_chart=other, mat_b=mat_b, mat_t=mat_t,
                           body_pixels=body_pixels, raster=raster)


@dataclass
class _EvalState(WorkerState):
    """A thread's opened inputs (and GL context) for one `_EvalSpec`."""

    texcoord_set: Any
    evaluator: ImageEvaluator


_EVAL_STATE = ThreadState()  # each thread's _EvalState, one set at a time


def _open_eval_state(ds, tc, ctx: GLContext, owns_ctx: bool) -> _EvalState:
    return _EvalState(ctx, owns_ctx, tc, ImageEvaluator(ctx, ds, tc.faces, tc.uv, tc.parent))


def _eval_state(spec: _EvalSpec) -> _EvalState:
    """A worker's state for an evaluation (one in this process puts its own in place up front)."""

    configure_threads(1)
    ds = load_dataset(spec.dataset, validate=False)
    tc = open_texcoords(spec.texcoords, ds.num_vertices)
    return _open_eval_state(ds, tc, GLContext(), True)


# The heatmaps' colour scales, the same in every picture of every run, so that two pictures
# compare at a glance (logarithmic; values above the top are drawn in its colour, "+").
UV_HEATMAP_SCALE = (1e-5, 3e-2)  # uv units
MATERIAL_HEATMAP_SCALE = (1e-5, 3e-2)  # meters: 0.01 to 30 mm


def heatmap_scales(has_material: bool = True) -> dict:
    """The `ColorScale`s of the eval heatmaps: "uv" (the uv error on same-chart pixels) and,
    with a rest shape, "material" (the material error, shown in mm)."""

    scales = {"uv": ColorScale(*UV_HEATMAP_SCALE, True, "jet", "uv error on same-chart pixels", "uv units")}
    if has_material:
        scales["material"] = ColorScale(*MATERIAL_HEATMAP_SCALE, True, "jet", "material error", "mm", 1e3)
    return scales


# How the heatmaps name a texcoord set by its source (texcoords.json "source").
SOURCE_NAMES = {"ts": "texture sliding", "tsnn": "learned model", "views-blend": "novel view (blend)",
                "views-reconstruct": "novel view (reconstruct)"}


def _heatmap_picture(image: ImageErrors, cam, source: str, pose: int) -> np.ndarray:
    """The inferred mesh (T_G) and the texcoord set side by side: the uv error on the pixels
    where both meshes show one UV chart (top row) and, with a rest shape, the material error
    (bottom row), each row on its fixed colour scale (`heatmap_scales`) with its colour bar.
    Each panel's label names the measure it maps with that image's value (SqrtMSE of the uv
    error over the same pixels, RMSE of the material error); a title names the pose and the
    camera; a legend the other colours (magenta: the two meshes show different UV charts,
    where a uv difference means nothing; grey: the body)."""

    raster = image.raster
    r0, r1, c0, c1 = raster.box
    shape = (cam.height, cam.width)

    def full(values, scale, charts: bool):
        box = np.full((r1 - r0) * (c1 - c0), np.nan, np.float32)
        box[image.pixels] = values
        err = raster.full(box.reshape(r1 - r0, c1 - c0), shape, np.nan)
        picture = heatmap(err, scale)
        marks = [(image.body_pixels, BODY_RGB)]
        if charts:
            marks.append((image.pixels[image.other_chart], CHART_BOUNDARY_COLOR))
        for where, color in marks:
            mark = np.zeros((r1 - r0) * (c1 - c0), bool)
            mark[where] = True
            picture[raster.full(mark.reshape(r1 - r0, c1 - c0), shape, False)] = color
        return picture

    (same_b, same_t), (m_b, m_t) = image.sqrt_mse_same_chart, image.material_rmse_m
    scales = heatmap_scales(image.mat_b is not None)
    source = SOURCE_NAMES.get(source, source)
    rows = [side_by_side([full(image.e_b, scales["uv"], True), full(image.e_t, scales["uv"], True),
                          colorbar(cam.height, scales["uv"], width=110)],
                         [f"inferred (T_G): same-chart uv error {same_b * 1e3:.2f}e-3",
                          f"{source}: same-chart uv error {same_t * 1e3:.2f}e-3", ""])]
    if image.mat_b is not None:
        rows.append(side_by_side([full(image.mat_b, scales["material"], False),
                                  full(image.mat_t, scales["material"], False),
                                  colorbar(cam.height, scales["material"], width=110)],
                                 [f"inferred (T_G): material error {m_b * 1e3:.2f} mm",
                                  f"{source}: material error {m_t * 1e3:.2f} mm", ""]))
    width = rows[0].shape[1]
    what = "uv error on same-chart pixels" + (" (top), material error (bottom)" if image.mat_b is not None else "")
    title = caption(f"pose {pose}, camera {cam.name}: {what}. Left: the inferred mesh with its own texture "
                    f"coordinates (T_G); right: {source}.", width)
    material = ", the material error (bottom row) is drawn" if image.mat_b is not None else ""
    entries = [(CHART_BOUNDARY_COLOR, "top row: the two meshes show different UV charts (pattern pieces) here; "
                                      f"the uv difference means nothing{material}"),
               (BODY_RGB, "the body is the nearest surface in either render"),
               (BACKGROUND, "background: no cloth in either render")]
    rows.append(legend(entries, width, scale=0.5))
    return stack([title] + rows)


def _eval_images(spec: _EvalSpec, jobs: list[tuple[int, int, str]]) -> list[tuple]:
    """Evaluate (job index, pose, camera name) images; returns (index, s_b, s_t, same_b,
    same_t, material_b, material_t, body_share) each (NaN material without a rest shape,
    NaN body share without a body)."""

    state = _EVAL_STATE.get(spec.key, lambda: _eval_state(spec))
    tc = state.texcoord_set
    out = []
    for index, k, name in jobs:
        cam = spec.rig[name]
        image = state.evaluator(k, cam, tc.texcoords(cam.name, k), assigned=tc.assigned(cam.name, k))
        original = ()
        if spec.original:  # the same pixels' errors with the original mesh as the baseline
            before = state.evaluator(k, cam, tc.uv, inferred=read_row(state.evaluator.dataset.original_inferred, k))
            original = (before.sqrt_mse[0], before.material_rmse_m[0])
        out.append((index, *image.values(), *original))
        if spec.heatmaps is not None:
            save_png(Path(spec.heatmaps) / f"pose_{k:05d}_{cam.name}.png",
                     _heatmap_picture(image, cam, tc.source, k))
    return out


@writer("eval", out="heatmaps", inputs=lambda a: (a["dataset"], a["texcoord_set"], a["rig"]))
def evaluate(dataset, rig, texcoord_set, *, poses: Sequence[int] | None = None,
             cameras: Sequence[str] | None = None, heatmaps: str | os.PathLike | None = None, progress: bool = True, workers: int = 1,
             scheduler: str | None = None, ctx: GLContext | None = None, overwrite: bool = False) -> Evaluation:
    """SqrtMSE of the baseline and of a texcoord set over poses and cameras (DESIGN §7).

    "inferred" is the baseline: the base inferred mesh with T_G. "texcoords" is the
    (subdivided) inferred mesh with the set's T_N for that camera. Images where the two
    meshes share no pixel are skipped.

    Args:
        dataset: `Dataset` or dataset directory.
        rig: `Rig` or rig path / built-in name. A rig whose cameras are all in the set
            selects those cameras; otherwise it must contain every camera of the set.
        cameras: evaluate these cameras of the rig and the set only (default: as above).
        texcoord_set: `TexcoordSet` or its directory.
        poses: dataset pose indices (default: the set's poses).
        heatmaps: if given, a directory that receives ``pose_<k>_<camera>.png`` per image:
            baseline and texcoords heatmaps side by side, the uv error on same-chart pixels
            (magenta where the two meshes show different UV charts) and, when the dataset has
            `rest`, the material error in millimeters, each measure on one logarithmic scale
            in every picture (`heatmap_scales`).
        progress: progress bar on stderr.
        workers: local processes (1: this process), see `mvtex.util.parallel.map_unordered`.
        scheduler: Dask scheduler address (overrides `workers`); its workers must read the
            same dataset and texcoord paths.
        ctx: the GL context for work in this process (one is created, and released, for this
            call if None); worker processes create their own.
        The result does not depend on `workers` or `scheduler`: images are gathered back
        into (pose, camera) order before any statistic is taken.

    Returns:
        An `Evaluation`; `.to_json()` is the JSON object of `mvtex eval --json`.
    """

    heatmaps = as_path(heatmaps, "heatmaps", optional=True)
    poses = None if poses is None else as_indices(poses, "poses")
    if cameras is not None and (isinstance(cameras, (str, bytes)) or not hasattr(cameras, "__iter__")
                                or not all(isinstance(c, str) for c in cameras)):
        raise OptionError("cameras", f"must be a list of camera names, got {cameras!r:.60}")

    check_backend(workers, scheduler)
    workers = 1 if workers is None else workers
    ds = as_dataset(dataset)
    ds.require_gt("the evaluation (eval)")
    if not isinstance(texcoord_set, (TexcoordSet, str, os.PathLike)):
        raise OptionError("texcoord_set", f"must be a TexcoordSet or a texcoord set folder path, got "
                          f"{type(texcoord_set).__name__}")
    tc = texcoord_set if isinstance(texcoord_set, TexcoordSet) else open_texcoords(texcoord_set, ds.num_vertices)
    tc.check_dataset(ds)
    rig = as_rig(rig)
    if cameras is not None:
        rig = rig.select(list(cameras))
    elif not set(rig.names) <= set(tc.cameras):
        rig = rig.select(tc.cameras)
    tc.check_rig(rig, cameras=rig.names)
    poses = tc.poses if poses is None else ds.check_poses(poses)  # in range, none twice, at least one
    if poses:
        check_sees(rig, read_row(ds.inferred, poses[0]),
                   what=f"the inferred mesh of {ds.path} at pose {poses[0]}")
    check_outside_body(rig, ds, poses)
    for p in poses:
        tc.row(p)  # InputError for a pose the set does not have
    for name in rig.names:
        tc.displacement(name, poses[0])  # validates the camera's arrays once, here
    # Heatmaps are drawn into a temporary folder renamed onto `heatmaps` when all are in, so
    # that the folder appears whole, with the manifest of what mvtex wrote there.
    with (atomic_path(heatmaps) if heatmaps is not None else contextlib.nullcontext()) as out_dir:
        if out_dir is not None:
            out_dir.mkdir()
        spec = _EvalSpec(dataset=str(Path(ds.path).resolve()), texcoords=str(Path(tc.path).resolve()), rig=rig,
                         heatmaps=None if out_dir is None else str(out_dir.resolve()), original=ds.corrected)
        local = workers <= 1 and not scheduler
        if local:  # this process: reuse what is open
            own = GLContext() if ctx is None else None
            _EVAL_STATE.set(spec.key, _open_eval_state(ds, tc, own or ctx, own is not None))
        jobs = [(i, k, name) for i, (k, name) in enumerate((k, c.name) for k in poses for c in rig)]
        chunk = max(1, min(8, len(jobs) // (4 * max(1, workers))))
        tasks = [(spec, jobs[i:i + chunk]) for i in range(0, len(jobs), chunk)]
        values: list = [None] * len(jobs)
        try:
            with tqdm(total=len(jobs), desc="eval", unit="image", disable=not progress, file=sys.stderr) as bar:
                for results in map_unordered(_eval_images, tasks, workers=workers, scheduler=scheduler):
                    for index, *image in results:
                        values[index] = image
                    bar.update(len(results))
        finally:
            if local:
                _EVAL_STATE.set(None, None)
    has_rest, has_body = ds.rest is not None, ds.body is not None
    per_cam: dict[str, list[tuple]] = {c.name: [] for c in rig}
    for (_, _, name), image in zip(jobs, values):
        per_cam[name].append(image)
    per_camera = {name: _summary(images, has_rest, has_body, has_original=ds.corrected)
                  for name, images in per_cam.items()}
    return _summary([v for images in per_cam.values() for v in images], has_rest, has_body, per_camera=per_camera,
                    has_original=ds.corrected)
