"""Throughput of texture sliding: the raster path against a ray-cast (Embree) path of the
same algorithm, measured side by side on the same jobs, with their agreement; and the
throughput of the per-pixel evaluation.

The ray-cast path differs from `sliding.find_hits_raster` only in how it finds things:
pixel ownership (rule 1) by casting a ray through every pixel centre of the inferred
mesh's bounding box, the depth test (rule 2) and the first gt hit by casting the vertex
rays (`trimesh.ray.ray_pyembree.RayMeshIntersector`, which needs `embreex`). Embree works
in float32, so its hit triangle is re-intersected in float64 for the barycentrics; every
rule after that (`sliding.displacement_from_hits`: back faces, edge breaking, fill) is shared.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import platform
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Sequence

import numpy as np
from tqdm import tqdm

from mvtex.data.camera import Camera
from mvtex.data.dataset import as_dataset, load_dataset, reference_shape
from mvtex.data.limits import MAX_SUBDIV
from mvtex.data.rig import Rig, as_rig, check_outside_body, check_sees
from mvtex.evaluation.evaluate import ImageEvaluator
from mvtex.render.context import GLContext
from mvtex.sliding.hits import Hits, find_hits_raster, in_front, intersect_pairs, owning_vertices
from mvtex.sliding.kernels import seen_from_inside as compiled_seen_from_inside
from mvtex.sliding.options import SlideOptions
from mvtex.sliding.pose import displacement_from_hits
from mvtex.sliding.topology import BodyTopology, SlideTopology, body_topology, build_topology
from mvtex.util.checks import as_index, as_indices
from mvtex.util.errors import OptionError
from mvtex.util.parallel import check_backend, configure_threads, worker_count

if TYPE_CHECKING:
    from mvtex.render.context import GLContext


def _intersector(positions: np.ndarray, faces: np.ndarray):
    import trimesh  # noqa: PLC0415 (loaded on use)
    from trimesh.ray.ray_pyembree import RayMeshIntersector  # noqa: PLC0415 (loaded on use)

    return RayMeshIntersector(trimesh.Trimesh(vertices=positions, faces=faces, process=False))


def _first_hits(intersector, origins: np.ndarray, dirs: np.ndarray, num_faces: int):
    """Nearest hit triangle per ray (-1 = none)."""
    tri, ray = intersector.intersects_id(origins, dirs, multiple_hits=False, return_locations=False)
    out = np.full(len(dirs), -1, np.int64)
    out[ray] = tri
    return out


def _first_t(intersector, origin: np.ndarray, dirs: np.ndarray, positions: np.ndarray, faces: np.ndarray):
    """Per ray: t (units of dirs) of Embree's first hit, re-intersected in float64 (inf for
    none: Embree's float32 hit can miss in float64 by a hair at an edge)."""
    unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    tri = _first_hits(intersector, np.broadcast_to(origin, unit.shape), unit, len(faces))
    t = np.full(len(dirs), np.inf)
    has = tri >= 0
    t[has] = intersect_pairs(origin, dirs[has], positions, faces, tri[has])[0]
    return t, tri


def find_hits_embree(gt: np.ndarray, inferred: np.ndarray, faces: np.ndarray, X: np.ndarray, topo: SlideTopology,
                     camera: Camera, options: SlideOptions, *,
                     body: tuple[np.ndarray, BodyTopology] | None = None) -> Hits:
    """Same contract as `sliding.find_hits_raster`, by ray casting with Embree (the body,
    if given, in a scene of its own: it is in the pixels' scene, hides a vertex it meets
    before the vertex and a gt hit it meets before the hit)."""

    n = len(X)
    origin = camera.center
    W, H = camera.width, camera.height
    m_sub = len(topo.faces)
    faces = np.asarray(faces, np.int64)
    X_all, sub_faces_all = X, topo.faces
    if body is not None:
        body_positions = np.asarray(body[0], np.float64)
        X_all = np.concatenate([X, body_positions])
        sub_faces_all = np.concatenate([topo.faces, body[1].faces + len(X)])
    pixels, z = camera.project(X)
    # Rule 1: cast a ray through every pixel centre of the projected bounding box.
    front = z > 0
    lo = np.clip(np.floor(pixels[front].min(axis=0)) - 1, 0, [W - 1, H - 1]).astype(int)
    hi = np.clip(np.ceil(pixels[front].max(axis=0)) + 1, 0, [W - 1, H - 1]).astype(int)
    cols, rows = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1))
    pix = np.stack([cols.ravel(), rows.ravel()], axis=1).astype(np.float64)
    dirs_px = camera.pixel_rays(pix)
    scene = _intersector(X_all, sub_faces_all)
    owner = _first_hits(scene, np.broadcast_to(origin, dirs_px.shape), dirs_px, len(sub_faces_all))
    owned = np.zeros(m_sub, bool)
    owned[owner[(owner >= 0) & (owner < m_sub)]] = True
    cand = owning_vertices(owned, topo, camera, pixels, z)
    # Rule 2: the first inferred surface along the vertex ray is not (much) nearer, and the
    # body is not nearer at all.
    dirs = X[cand] - origin
    t_occ, _ = _first_t(scene if body is None else _intersector(X, topo.faces), origin, dirs, X, topo.faces)
    t_body = np.full(len(cand), np.inf)
    if body is not None:
        t_body, _ = _first_t(_intersector(body_positions, body[1].faces), origin, dirs, body_positions,
                             body[1].faces)
    vis = in_front(t_occ, options) & ~(t_body < 1)
    cand, dirs, t_body = cand[vis], dirs[vis], t_body[vis]
    visible = np.zeros(n, bool)
    visible[cand] = True
    # Rule 3: the first gt hit, none where the body comes first (exact ties go to the cloth).
    t_gt, tri = _first_t(_intersector(gt, faces), origin, dirs, gt, faces)
    tri[t_gt > t_body * (1 + 1e-9)] = -1
    tri_hit = np.full(n, -1, np.int64)
    bary = np.zeros((n, 3))
    back = np.zeros(n, bool)
    ok = tri >= 0
    t, b1, b2, facing = intersect_pairs(origin, dirs[ok], gt, faces, tri[ok])
    idx = cand[ok]
    tri_hit[idx] = tri[ok]
    bary[idx] = np.stack([1 - b1 - b2, b1, b2], axis=1)
    back[idx] = facing > 0
    return Hits(visible=visible, tri=tri_hit, bary=bary, back=back,
                from_inside=compiled_seen_from_inside(np.ascontiguousarray(X, dtype=np.float64), topo.faces,
                                                      np.ascontiguousarray(origin, dtype=np.float64)))


def _job(ctx: GLContext, path: str, gt, inferred, faces, uv, topo, camera, options, body=None):
    """One sliding job on `path` ("raster" or "raycast"); body: (positions, BodyTopology) or None."""
    gt = np.asarray(gt, np.float64)
    inferred = np.asarray(inferred, np.float64)
    X = topo.positions(inferred)
    if path == "raster":
        hits = find_hits_raster(ctx, gt, inferred, faces, X, topo, camera, options, body=body)
    else:
        hits = find_hits_embree(gt, inferred, faces, X, topo, camera, options, body=body)
    return displacement_from_hits(hits, faces, uv, X, topo, options)


def _bodies(ds, topo: SlideTopology, poses) -> dict:
    """Pose -> (body positions, BodyTopology) of a dataset with a body, else pose -> None."""
    if ds.body is None:
        return {k: None for k in poses}
    body_topo = body_topology(ds.body.faces, topo)
    return {k: (ds.body.pose(k), body_topo) for k in poses}


def _worker_pass(dataset_path: str, rig: Rig, jobs: list, subdiv: int, repeats: int, barrier) -> tuple[int, float]:
    """In a worker process: warm up, wait for the other workers, then time `repeats`
    passes over `jobs` ((pose, camera name) pairs) on the raster path. Returns (number of
    jobs, fastest pass in seconds)."""

    configure_threads(1)
    ds = load_dataset(dataset_path, validate=False)
    options = SlideOptions(subdiv=subdiv)
    topo = build_topology(ds.faces, ds.uv, reference_shape(ds), subdiv)
    faces = ds.faces.astype(np.int64)
    bodies = _bodies(ds, topo, sorted({k for k, _ in jobs}))
    with GLContext() as ctx:
        k0 = jobs[0][0]
        _job(ctx, "raster", ds.gt[k0], ds.inferred[k0], faces, ds.uv, topo, rig[jobs[0][1]], options, bodies[k0])
        barrier.wait()
        best = np.inf
        for _ in range(repeats):
            start = time.perf_counter()
            for k, cam in jobs:
                _job(ctx, "raster", ds.gt[k], ds.inferred[k], faces, ds.uv, topo, rig[cam], options, bodies[k])
            best = min(best, time.perf_counter() - start)
    return len(jobs), best


def _bench_workers(dataset_path: str, rig: Rig, jobs: list, subdiv: int, repeats: int, workers: int) -> float:
    """Raster-path jobs/s of `workers` processes running side by side, each on its share
    of the jobs (start-up, topology and warm-up excluded: the processes start timing
    together, behind a barrier)."""

    workers = worker_count(workers)  # never more processes than cores
    ctx = mp.get_context("spawn")
    with ctx.Manager() as manager, ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
        barrier = manager.Barrier(workers)
        shares = [jobs[w::workers] for w in range(workers)]
        futures = [pool.submit(_worker_pass, dataset_path, rig, share, subdiv, repeats, barrier) for share in shares]
        done = [f.result() for f in futures]
    return sum(count for count, _ in done) / max(seconds for _, seconds in done)


@dataclass(frozen=True)
class BenchResult:
    """What `run_bench` measured (`to_json()` is `mvtex bench --json`).

    Attributes:
        jobs, poses, cameras, subdiv, num_vertices, image_size: what was timed.
        sliding: {"raster"|"raycast": {"jobs_per_s", "seconds"} (one process, the fastest pass;
            with the dataset's body when it has one), "raster_workers": {"workers",
            "jobs_per_s"} (None when workers == 1)}.
        body: for a dataset with a body, {"num_faces", "raster_without_body": {"jobs_per_s",
            "seconds"}, "overhead": raster seconds with the body / without - 1}, measured side
            by side; None without a body.
        speedup: raster over ray cast, measured side by side.
        agreement: {"displacement": share of vertices assigned by both paths whose d agree to
            1e-5, "assigned_flags": share with equal flags}.
        eval: {"images_per_s"}. machine: cores, GL renderer, platform, Python.
    """

    jobs: int
    poses: int
    cameras: list[str]
    subdiv: int
    num_vertices: int
    image_size: list[int]
    sliding: dict
    body: dict | None
    speedup: float
    agreement: dict
    eval: dict
    machine: dict

    def to_json(self) -> dict:
        return asdict(self)

    def summary(self) -> str:
        """A readable summary, the sliding throughput first (`mvtex bench` without --json)."""
        def rate(entry) -> str:
            return "n/a" if not entry or entry.get("jobs_per_s") is None else f"{entry['jobs_per_s']:.1f} jobs/s"

        s = self.sliding
        lines = [f"sliding: {rate(s.get('raster'))} (raster, 1 process), {rate(s.get('raycast'))} (Embree ray cast); "
                 f"raster / ray cast {self.speedup:.2f}x, measured side by side"]
        if s.get("raster_workers") and s["raster_workers"].get("jobs_per_s") is not None:
            lines.append(f"  {rate(s['raster_workers'])} on {s['raster_workers'].get('workers')} worker processes")
        if self.body:
            lines.append(f"  the body ({self.body.get('num_faces')} faces) costs {100 * self.body['overhead']:.0f} % "
                         f"(without it {rate(self.body.get('raster_without_body'))})")
        agree = self.agreement
        lines.append(f"raster and ray cast agree: displacement {100 * agree.get('displacement', float('nan')):.2f} %, "
                     f"assigned flags {100 * agree.get('assigned_flags', float('nan')):.2f} % of vertices")
        lines.append(f"eval: {self.eval.get('images_per_s', float('nan')):.1f} images/s")
        lines.append(f"timed: {self.jobs} (pose, camera) jobs ({self.poses} poses x {len(self.cameras)} cameras), "
                     f"subdiv {self.subdiv}, {self.num_vertices} vertices, {self.image_size[0]}x{self.image_size[1]} "
                     f"pixels; {self.machine.get('cpu_count', '?')} cores, {self.machine.get('gl_renderer', '?')}")
        return "\n".join(lines)


def run_bench(dataset, rig, *, poses: Sequence[int] | None = None, subdiv: int = 1, repeats: int = 3,
              progress: bool = True, workers: int = 2, ctx: GLContext | None = None) -> BenchResult:
    """Measure jobs/s of the raster and ray-cast sliding paths and the eval throughput.

    Args:
        dataset: `Dataset` or directory. rig: `Rig` or rig path / built-in name.
        poses: pose indices (default: the first 20).
        subdiv: subdivision levels of the sliding jobs.
        repeats: timed passes over all jobs per path; the fastest pass is reported.
        progress: progress bar on stderr.
        workers: also measure the raster path on this many processes side by side
            (`slide_jobs.slide_dataset(workers=...)`); 1 = skip.
        ctx: `raster.GLContext` for this process (created, and released, if None).

    Returns:
        A `BenchResult`.
    """

    poses = None if poses is None else as_indices(poses, "poses")
    subdiv, repeats = as_index(subdiv, "subdiv"), as_index(repeats, "repeats")
    if not 0 <= subdiv <= MAX_SUBDIV:
        raise OptionError("subdiv", f"must be an integer in [0, {MAX_SUBDIV}], got {subdiv}")
    if not 1 <= repeats <= 100:
        raise OptionError("repeats", f"must be an integer in [1, 100], got {repeats}")

    check_backend(workers)
    ds = as_dataset(dataset)
    ds.require_gt("the sliding benchmark (bench)")
    rig = as_rig(rig)
    poses = list(range(min(20, ds.num_poses))) if poses is None else ds.check_poses(poses)
    check_sees(rig, np.asarray(ds.inferred[poses[0]]),
               what=f"the inferred mesh of {ds.path} at pose {poses[0]}")
    check_outside_body(rig, ds, poses)
    if ctx is None:
        with GLContext() as own:
            return run_bench(ds, rig, poses=poses, subdiv=subdiv, repeats=repeats, progress=progress,
                             workers=workers, ctx=own)

    options = SlideOptions(subdiv=subdiv)
    topo = build_topology(ds.faces, ds.uv, reference_shape(ds), subdiv)
    faces = ds.faces.astype(np.int64)
    jobs = [(k, cam) for k in poses for cam in rig]
    gts = {k: np.asarray(ds.gt[k], np.float64) for k in poses}
    infs = {k: np.asarray(ds.inferred[k], np.float64) for k in poses}
    bodies = _bodies(ds, topo, poses)
    # (name, path, with the body): the body-free raster pass only for a dataset with a body.
    passes = [("raster", "raster", True), ("raycast", "raycast", True)]
    if ds.body is not None:
        passes.append(("raster_without_body", "raster", False))
    # Warm up every path (GL context, shader compilation, Embree import).
    for _, path, worn in passes:
        _job(ctx, path, gts[poses[0]], infs[poses[0]], faces, ds.uv, topo, rig.cameras[0], options,
             bodies[poses[0]] if worn else None)
    results: dict = {}
    bar = tqdm(total=len(passes) * repeats * len(jobs), desc="bench", unit="job", disable=not progress,
               file=sys.stderr)
    # The passes of the paths alternate, so that all meet the same moments of a shared
    # machine; the fastest pass of each counts.
    timing = {name: np.inf for name, _, _ in passes}
    for _ in range(repeats):
        for name, path, worn in passes:
            start = time.perf_counter()
            for k, cam in jobs:
                results[name, k, cam.name] = _job(ctx, path, gts[k], infs[k], faces, ds.uv, topo, cam, options,
                                                  bodies[k] if worn else None)
                bar.update(1)
            timing[name] = min(timing[name], time.perf_counter() - start)
    bar.close()
    parallel = None
    if workers > 1:
        parallel = _bench_workers(str(ds.path), rig, [(k, cam.name) for k, cam in jobs], subdiv, repeats, workers)
    both = agree = flags = total = 0
    for k, cam in jobs:
        d_r, a_r = results["raster", k, cam.name]
        d_e, a_e = results["raycast", k, cam.name]
        common = a_r & a_e
        both += int(common.sum())
        agree += int((np.abs(d_r[common] - d_e[common]).max(axis=1) <= 1e-5).sum())
        flags += int((a_r == a_e).sum())
        total += len(a_r)
    # Evaluation: what `evaluate` does per image (uv and material errors, baseline and
    # texcoords, the body in the renders), on the raster path's texcoords.
    evaluator = ImageEvaluator(ctx, ds, topo.faces, topo.uv, topo.subdivision.parent)
    k0, cam0 = jobs[0]
    evaluator(k0, cam0, topo.uv + results["raster", k0, cam0.name][0], gt=gts[k0], inferred=infs[k0])  # warm-up
    eval_time = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        for k, cam in jobs:
            evaluator(k, cam, topo.uv + results["raster", k, cam.name][0], gt=gts[k], inferred=infs[k])
        eval_time = min(eval_time, time.perf_counter() - start)
    body = None
    if ds.body is not None:
        body = {"num_faces": int(len(ds.body.faces)),
                "raster_without_body": {"jobs_per_s": len(jobs) / timing["raster_without_body"],
                                        "seconds": timing["raster_without_body"]},
                "overhead": timing["raster"] / timing["raster_without_body"] - 1}
    return BenchResult(
        jobs=len(jobs), poses=len(poses), cameras=rig.names, subdiv=subdiv, num_vertices=len(topo.uv),
        image_size=[rig.cameras[0].width, rig.cameras[0].height],
        sliding={"raster": {"jobs_per_s": len(jobs) / timing["raster"], "seconds": timing["raster"]},
                 "raycast": {"jobs_per_s": len(jobs) / timing["raycast"], "seconds": timing["raycast"]},
                 "raster_workers": {"workers": int(workers), "jobs_per_s": parallel}},
        body=body, speedup=timing["raycast"] / timing["raster"],
        agreement={"displacement": agree / max(both, 1), "assigned_flags": flags / max(total, 1)},
        eval={"images_per_s": len(jobs) / eval_time},
        machine={"cpu_count": os.cpu_count(), "gl_renderer": ctx.renderer, "platform": platform.platform(),
                 "python": platform.python_version(), "processes": 1})
