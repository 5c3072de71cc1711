"""Texture sliding over a whole dataset (DESIGN §5 step 7): every (pose, camera) job of
`mvtex.sliding.pose.slide_pose`, streamed into a texcoord set (DESIGN §4), resumable, on local
processes or a Dask cluster.

The pose-independent topology is built once from `mvtex.data.dataset.reference_shape`, in the
main process and in every worker alike, so the result of a pose does not depend on the
pose subset, on their order or on the number of workers.
"""

from __future__ import annotations

import json
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from mvtex.data.dataset import as_dataset, load_dataset, reference_shape, reference_shape_source
from mvtex.data.partial_set import PartialSet
from mvtex.data.rig import Rig, as_rig, check_outside_body, check_sees, save_rig
from mvtex.data.texcoord_header import TexcoordHeader
from mvtex.data.texcoords import RIG_FILE, dataset_record, rig_record
from mvtex.render.context import GLContext
from mvtex.sliding.options import SlideOptions
from mvtex.sliding.pose import slide_pose
from mvtex.sliding.topology import BodyTopology, SlideTopology, body_topology, build_topology
from mvtex.util.checks import as_path, check_instance
from mvtex.util.errors import InputError
from mvtex.util.files import dumps_strict, load_npy, read_row
from mvtex.util.fingerprint import fingerprint, fingerprint_record
from mvtex.util.output import writer
from mvtex.util.parallel import ThreadState, WorkerState, check_backend, configure_threads, map_unordered, worker_count

if TYPE_CHECKING:
    from mvtex.data.dataset import Dataset

_CHUNK = 8  # poses per task: amortises task overhead, keeps results small (≈1 MB)


_AUTO_WORKERS = 8  # workers=None: one process per core, up to this many


_AUTO_MIN_JOBS = 256  # workers=None: fewer jobs left than this run in this process (start-up ≈ 1-2 s a worker)


@dataclass(frozen=True)
class _Spec:
    """What a worker needs to slide chunks of poses: picklable; its state is kept per thread by key."""

    dataset: str
    rig: Rig
    options: SlideOptions
    key: str


@dataclass
class _WorkerState(WorkerState):
    """What one thread keeps between chunks of one run: the dataset, its topology (and the
    GL context)."""

    dataset: Dataset
    topology: SlideTopology
    body_topo: BodyTopology | None


def _body_topology(ds: Dataset, topo: SlideTopology) -> BodyTopology | None:
    body = ds.body
    return None if body is None else body_topology(body.faces, topo)


_WORKER = ThreadState()


def _open_state(spec: _Spec) -> _WorkerState:
    """A worker's state for a run (a run in this process puts its own in place up front)."""

    configure_threads(1)
    ds = load_dataset(spec.dataset, validate=False)
    topo = build_topology(ds.faces, ds.uv, reference_shape(ds), spec.options.subdiv)
    return _WorkerState(GLContext(), True, ds, topo, _body_topology(ds, topo))


def _slide_chunk(spec: _Spec, camera: str, rows: list[int], poses: list[int]):
    """Slide poses[rows] for one camera; returns (camera, rows, d (r,n',2), assigned (r,n'))."""
    state = _WORKER.get(spec.key, lambda: _open_state(spec))
    ds, topo = state.dataset, state.topology
    cam = spec.rig[camera]
    d_out = np.empty((len(rows), len(topo.uv), 2), np.float32)
    a_out = np.empty((len(rows), len(topo.uv)), bool)
    for i, row in enumerate(rows):
        k = poses[row]
        # Read through the files (`read_row`): rows read through the dataset's maps would stay
        # resident, and a long run would end up holding the whole dataset.
        body = None if state.body_topo is None else (ds.body.pose(k), ds.body.faces)
        d_out[i], a_out[i] = slide_pose(read_row(ds.gt, k), read_row(ds.inferred, k),
                                        ds.faces, ds.uv, cam, topo.subdivision, spec.options, topology=topo,
                                        ctx=state.ctx, body=body, body_topo=state.body_topo)
    return camera, rows, d_out, a_out


@writer("slide", inputs=lambda a: (a["dataset"], a["rig"]))
def slide_dataset(dataset, rig, out: str | os.PathLike, *, poses: list[int], options: SlideOptions,
                  cameras: list[str] | None = None, workers: int | None = None, scheduler: str | None = None,
                  progress: bool = True, ctx: GLContext | None = None, overwrite: bool = False) -> Path:
    """Texture-slide every (pose, camera) of a dataset into a texcoord set (DESIGN §4).

    Results stream into memory-mapped .npy files in ``<out>.partial/``; a per-camera done
    mask (``done.npy``) is saved after the data of every chunk is flushed, so an
    interrupted run continues where it stopped when called again with the same arguments,
    and a finished one returns at once (`slide_complete`). The set records its cameras in
    ``rig.yaml``.
    Called with different options, poses, cameras, rig, dataset (path or content) or
    reference shape, it discards the partial result (saying so on stderr) and starts over.
    When every job is done the directory is renamed to `out` (an older `out` is renamed
    aside first and deleted after).

    texcoords.json records "reference": which shape (`dataset.reference_shape`) the
    topology, seam groups, fill Laplacian and edge breaking were measured on, and its
    fingerprint.

    Args:
        dataset: a `Dataset` or a dataset directory.
        rig: a `Rig` or a rig path / built-in rig name.
        out: the texcoord set directory to write.
        poses: dataset pose indices (rows of the set, in this order).
        options: SlideOptions (recorded in texcoords.json as "options").
        cameras: camera names (default: every camera of the rig).
        workers: local processes (each with its own GL context); 1 = this process; None =
            up to `_AUTO_WORKERS` (one per CPU core) when at least `_AUTO_MIN_JOBS` jobs are
            left (a process takes about a second to start), else 1.
        scheduler: Dask scheduler address (overrides `workers`).
        progress: show a progress bar on stderr.
        ctx: `raster.GLContext` for the jobs run in this process (created, and released at
            the end, if None); worker processes create their own.
        overwrite: replace another command's output at `out` (never files mvtex did not
            write, never an input: the writer policy of `mvtex.util.output`).

    Returns:
        Path of the finished texcoord set.
    """

    check_backend(workers, scheduler)
    out = as_path(out, "out")
    check_instance(options, SlideOptions, "options")
    ds = as_dataset(dataset)
    ds.require_gt("texture sliding (slide)")
    rig = as_rig(rig).select(cameras)
    poses = ds.check_poses(poses)
    check_sees(rig, read_row(ds.inferred, poses[0]), what=f"the inferred mesh of {ds.path} at pose {poses[0]}")
    check_outside_body(rig, ds, poses)
    out = Path(out)
    record = _slide_record(ds, rig, options)
    if _complete(out, record, poses, rig.names, options.subdiv):
        if progress:
            print(f"{out}: complete, made with these options from these inputs; nothing to do", file=sys.stderr)
        return out
    reference = reference_shape(ds)
    topo = build_topology(ds.faces, ds.uv, reference, options.subdiv)
    partial = PartialSet(out, "slide", "ts", faces=topo.faces, uv=topo.uv, parent=topo.subdivision.parent, source="ts",
                         subdiv=options.subdiv, poses=poses, cameras=rig.names, record=record)
    tasks = []
    for c in rig.names:
        todo = partial.todo(c)
        for i in range(0, len(todo), _CHUNK):
            tasks.append((c, todo[i:i + _CHUNK]))
    left = sum(len(r) for _, r in tasks)
    if workers is None:
        workers = min(_AUTO_WORKERS, os.cpu_count() or 1) if left >= _AUTO_MIN_JOBS else 1
    workers = worker_count(workers)  # never more processes than cores: more would only take memory
    # Smaller tasks when they would not keep every worker busy.
    if workers > 1 and not scheduler and len(tasks) < 4 * workers:
        tasks = [(c, rows[i:i + 2]) for c, rows in tasks for i in range(0, len(rows), 2)]
    spec = _Spec(dataset=str(ds.path), rig=rig, options=options,
                 key=fingerprint_record(record))
    own_ctx = None
    if workers == 1 and not scheduler:
        # The jobs run in this process and reuse what was just built.
        if ctx is None:

            ctx = own_ctx = GLContext()
        _WORKER.set(spec.key, _WorkerState(ctx, False, ds, topo, _body_topology(ds, topo)))

    bar = tqdm(total=len(poses) * len(rig), initial=partial.rows_done, desc="slide", unit="job",
               disable=not progress, file=sys.stderr)
    try:
        for cam, rows, d, a in map_unordered(_slide_chunk, [(spec, c, rows, poses) for c, rows in tasks],
                                             workers=workers, scheduler=scheduler):
            partial.write(cam, rows, d, a)  # after every chunk: a stop loses at most the chunks in flight
            bar.update(len(rows))
    finally:
        bar.close()
        _WORKER.set(None, None)
        if own_ctx is not None:
            own_ctx.release()
    save_rig(rig, partial.path / RIG_FILE, overwrite=True)  # the set records its cameras (the unfinished set is mvtex's)
    return partial.finish()


def slide_complete(dataset, rig, out: str | os.PathLike, *, poses: list[int], options: SlideOptions,
                   cameras: list[str] | None = None) -> bool:
    """Whether `out` already holds the finished result of `slide_dataset` with these
    arguments (same poses, cameras, options, rig and dataset content): calling it again
    returns at once."""

    ds = as_dataset(dataset)
    ds.require_gt("texture sliding (slide)")
    rig = as_rig(rig).select(cameras)
    poses = ds.check_poses(poses)
    return _complete(Path(out), _slide_record(ds, rig, options), poses, rig.names, options.subdiv)


def _slide_record(ds, rig, options: SlideOptions) -> dict:
    """What texcoords.json records of a slide run besides its header (as the file holds it)."""

    record = {
        "options": options.to_json(),
        "dataset": dataset_record(ds),  # content, not only the path: arrays replaced in place must not be mixed
        "reference": {"shape": reference_shape_source(ds), "fingerprint": fingerprint(reference_shape(ds))},
        "rig": rig_record(rig),
    }
    return json.loads(dumps_strict(record))


def _complete(out: Path, record: dict, poses: list[int], cameras: list[str], subdiv: int) -> bool:
    """Whether `out` is a finished slide set of this run: texcoords.json with the same
    poses, cameras, subdivision and record, and every camera's arrays in their shapes."""

    if not (out / "texcoords.json").is_file() or (out.with_name(out.name + ".partial")).exists():
        return False
    try:
        wanted = TexcoordHeader(source="ts", subdiv=subdiv, poses=tuple(poses), cameras=tuple(cameras), record=record)
        if not wanted.same_run(TexcoordHeader.peek(out)):
            return False
        for cam in cameras:
            d = load_npy(out / cam / "displacement.npy")
            a = load_npy(out / cam / "assigned.npy")
            if d.shape[:1] != (len(poses),) or a.shape != d.shape[:2] or d.shape[2:] != (2,):
                return False
            del d, a
    except (InputError, OSError, ValueError, KeyError):
        return False
    return True
