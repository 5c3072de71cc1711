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
"""

from __future__ import annotations

import os
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from mvtex.data.rig import Rig, check_sees
from mvtex.util.files import read_row
from mvtex.util.parallel import ThreadState, WorkerState, check_backend

if TYPE_CHECKING:
    from mvtex.render.context import GLContext
from mvtex.evaluation.material import MATERIAL_HEATMAP_MAX_MM, MaterialMap, _material_error, _material_points
from mvtex.evaluation.uv import CHART_BOUNDARY_COLOR, HEATMAP_MAX, chart_image, masked_uv_error, texcoord_image


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
        per_camera: camera name -> the same for its images (no `per_camera` of its own).
    """

    num_images: int
    sqrt_mse: Comparison
    sqrt_mse_same_chart: Comparison
    material_rmse_m: Comparison | None
    per_camera: dict[str, "Evaluation"] = field(default_factory=dict)

    @property
    def ratio(self) -> float:
        return self.sqrt_mse.ratio

    @property
    def ratio_same_chart(self) -> float:
        return self.sqrt_mse_same_chart.ratio

    @property
    def ratio_material(self) -> float | None:
        return None if self.material_rmse_m is None else self.material_rmse_m.ratio

    def to_json(self) -> dict:
        """The JSON object of `mvtex eval --json`."""
        out = {"num_images": self.num_images,
               "sqrt_mse": self.sqrt_mse.to_json(), "ratio": self.ratio,
               "sqrt_mse_same_chart": self.sqrt_mse_same_chart.to_json(), "ratio_same_chart": self.ratio_same_chart,
               "material_rmse_m": None if self.material_rmse_m is None else self.material_rmse_m.to_json(),
               "ratio_material": self.ratio_material}
        if self.per_camera:
            out["per_camera"] = {name: e.to_json() for name, e in self.per_camera.items()}
        return out


def _summary(base: list[float], tc: list[float], base_same: list[float], tc_same: list[float],
             base_material: list[float] | None = None, tc_material: list[float] | None = None,
             per_camera: dict[str, Evaluation] | None = None) -> Evaluation:
    """Per-image errors (NaN where an image does not count) -> an `Evaluation` over the
    images where both the baseline and the texcoords have an error."""
    ok = [i for i in range(len(base)) if np.isfinite(base[i]) and np.isfinite(tc[i])]

    def compare(b, t):
        return None if b is None else Comparison(Stats.of([b[i] for i in ok]), Stats.of([t[i] for i in ok]))

    return Evaluation(num_images=len(ok), sqrt_mse=compare(base, tc), sqrt_mse_same_chart=compare(base_same, tc_same),
                      material_rmse_m=compare(base_material, tc_material), per_camera=per_camera or {})


@dataclass(frozen=True)
class _EvalSpec:
    """What a worker needs to evaluate images: picklable; its opened inputs are kept per thread by key."""

    dataset: str
    texcoords: str
    rig: Rig
    heatmaps: str | None

    @property
    def key(self) -> tuple[str, str]:
        return self.dataset, self.texcoords


@dataclass
class _EvalState(WorkerState):
    """A thread's opened inputs (and GL context) for one `_EvalSpec`."""

    dataset: Any
    texcoord_set: Any
    charts: np.ndarray
    charts_tc: np.ndarray
    material_map: MaterialMap | None


_EVAL_STATE = ThreadState()  # each thread's _EvalState, one set at a time


def _open_eval_state(ds, tc, ctx: GLContext, owns_ctx: bool) -> _EvalState:
    from mvtex.data.mesh import charts_through_parent, uv_charts

    charts = uv_charts(ds.faces, ds.num_vertices)
    material_map = MaterialMap(ds.faces, ds.uv, ds.rest, ctx=ctx) if ds.rest is not None else None
    return _EvalState(ctx, owns_ctx, ds, tc, charts, charts_through_parent(charts, tc.faces, len(tc.uv)),
                      material_map)


def _eval_state(spec: _EvalSpec) -> _EvalState:
    """A worker's state for an evaluation (one in this process puts its own in place up front)."""
    from mvtex.data.dataset import load_dataset
    from mvtex.data.texcoords import open_texcoords
    from mvtex.render.context import GLContext
    from mvtex.util.parallel import configure_threads

    configure_threads(1)
    ds = load_dataset(spec.dataset, validate=False)
    tc = open_texcoords(spec.texcoords, ds.num_vertices)
    return _open_eval_state(ds, tc, GLContext(), True)


def _eval_images(spec: _EvalSpec, jobs: list[tuple[int, int, str]]) -> list[tuple]:
    """Evaluate (job index, pose, camera name) images; returns (index, s_b, s_t, same_b,
    same_t, material_b, material_t) each (NaN material without a rest shape)."""
    from mvtex.render.pictures import colorbar, heatmap, side_by_side
    from mvtex.util.files import save_png

    state = _EVAL_STATE.get(spec.key, lambda: _eval_state(spec))
    ds, tc, ctx, material_map = state.dataset, state.texcoord_set, state.ctx, state.material_map
    charts, charts_tc = state.charts, state.charts_tc
    out = []
    for index, k, name in jobs:
        cam = spec.rig[name]
        # Through the files (`read_row`): rows read through the dataset's maps stay resident.
        gt = read_row(ds.gt, k).astype(np.float64)
        inferred = read_row(ds.inferred, k).astype(np.float64)
        uv_g, raster_g = texcoord_image(ctx, gt, ds.faces, ds.uv, cam)
        uv_b, raster_b = texcoord_image(ctx, inferred, ds.faces, ds.uv, cam)
        uv_t, raster_t = texcoord_image(ctx, tc.positions(inferred), tc.faces, tc.texcoords(cam.name, k), cam)
        chart_g, chart_b = chart_image(raster_g, ds.faces, charts), chart_image(raster_b, ds.faces, charts)
        chart_t = chart_image(raster_t, tc.faces, charts_tc)
        err_b, s_b = masked_uv_error(uv_b, chart_b >= 0, uv_g, chart_g >= 0)
        err_t, s_t = masked_uv_error(uv_t, chart_t >= 0, uv_g, chart_g >= 0)
        same_b = masked_uv_error(uv_b, chart_b == chart_g, uv_g, chart_g >= 0)[1]
        same_t = masked_uv_error(uv_t, chart_t == chart_g, uv_g, chart_g >= 0)[1]
        mat_err_b = mat_err_t = None
        m_b = m_t = float("nan")
        if material_map is not None:
            m_g = _material_points(raster_g, ds.faces, ds.rest)
            mat_err_b, m_b = _material_error(_material_points(raster_b, ds.faces, ds.rest), raster_b.mask, m_g,
                                             raster_g.mask)
            mat_err_t, m_t = _material_error(material_map(uv_t[raster_t.mask]), raster_t.mask, m_g, raster_g.mask)
        out.append((index, s_b, s_t, same_b, same_t, m_b, m_t))
        if spec.heatmaps is not None:
            panels = []
            for err, chart, total, same in ((err_b, chart_b, s_b, same_b), (err_t, chart_t, s_t, same_t)):
                image = heatmap(err, HEATMAP_MAX)
                image[(chart >= 0) & (chart_g >= 0) & (chart != chart_g)] = CHART_BOUNDARY_COLOR
                panels.append((image, f"{total * 1e3:.2f}e-3, same chart {same * 1e3:.2f}e-3"))
            picture = side_by_side([panels[0][0], panels[1][0], colorbar(cam.height, HEATMAP_MAX, unit="uv")],
                                   [f"inferred {panels[0][1]}", f"{tc.source} {panels[1][1]}", ""])
            if material_map is not None:
                row = side_by_side([heatmap(mat_err_b * 1e3, MATERIAL_HEATMAP_MAX_MM),
                                    heatmap(mat_err_t * 1e3, MATERIAL_HEATMAP_MAX_MM),
                                    colorbar(cam.height, MATERIAL_HEATMAP_MAX_MM, unit="mm")],
                                   [f"inferred material {m_b * 1e3:.2f} mm", f"{tc.source} material {m_t * 1e3:.2f} mm",
                                    ""])
                picture = np.concatenate([picture, np.full((4, picture.shape[1], 3), 255, np.uint8), row])
            save_png(Path(spec.heatmaps) / f"pose_{k:05d}_{cam.name}.png", picture)
    return out


def evaluate(dataset, rig, texcoord_set, *, poses: Sequence[int] | None = None,
             cameras: Sequence[str] | None = None, heatmaps: str | os.PathLike | None = None, progress: bool = True, workers: int = 1,
             scheduler: str | None = None, ctx: GLContext | None = None) -> Evaluation:
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
            baseline and texcoords heatmaps side by side (blue = 0, red >= 0.04; magenta where
            the two meshes show different UV charts) and, when the dataset has `rest`, a
            second row with the material error in millimetres (red >= 20 mm).
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
    from tqdm import tqdm

    from mvtex.data.dataset import as_dataset
    from mvtex.data.rig import as_rig
    from mvtex.data.texcoords import TexcoordSet, open_texcoords
    from mvtex.render.context import GLContext
    from mvtex.util.parallel import map_unordered

    check_backend(workers, scheduler)
    ds = as_dataset(dataset)
    tc = texcoord_set if isinstance(texcoord_set, TexcoordSet) else open_texcoords(texcoord_set, ds.num_vertices)
    tc.check_dataset(ds)
    rig, rig_source = as_rig(rig)
    if cameras is not None:
        rig = rig.select(list(cameras), source=rig_source)
    elif not set(rig.names) <= set(tc.cameras):
        rig = rig.select(tc.cameras, source=rig_source)
    tc.check_rig(rig, rig_source, cameras=rig.names)
    poses = tc.poses if poses is None else [int(p) for p in poses]
    if poses:
        check_sees(rig, read_row(ds.inferred, poses[0]), rig_source,
                   what=f"the inferred mesh of {ds.path} at pose {poses[0]}")
    for p in poses:
        tc.row(p)  # InputError for a pose the set does not have
    for name in rig.names:
        tc.displacement(name, poses[0])  # validates the camera's arrays once, here
    out_dir = Path(heatmaps) if heatmaps is not None else None
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
    spec = _EvalSpec(dataset=str(Path(ds.path).resolve()), texcoords=str(Path(tc.path).resolve()), rig=rig,
                     heatmaps=None if out_dir is None else str(out_dir.resolve()))
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
    has_rest = ds.rest is not None
    per_cam: dict[str, tuple[list, ...]] = {c.name: ([], [], [], [], [], []) for c in rig}
    for (_, _, name), image in zip(jobs, values):
        for column, value in zip(per_cam[name], image):
            column.append(value)
    per_camera = {name: _summary(*lists[:4], *(lists[4:] if has_rest else (None, None)))
                  for name, lists in per_cam.items()}
    return _summary(*([v for c in per_cam.values() for v in c[i]] if i < 4 or has_rest else None for i in range(6)),
                    per_camera=per_camera)
