"""`mvtex views`: a texcoord set whose cameras are novel views of an array, built block by
block of poses, resumable, on local processes or a Dask cluster.
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
from tqdm import tqdm

from mvtex.data.camera import Camera, check_camera_name
from mvtex.data.dataset import as_dataset, load_dataset
from mvtex.data.partial_set import PartialSet
from mvtex.data.rig import Rig, as_rig, check_outside_body, save_rig
from mvtex.data.texcoords import as_texcoords, dataset_record, open_texcoords, rig_record
from mvtex.util.checks import as_indices, as_path, check_instance
from mvtex.util.errors import InputError, OptionError
from mvtex.util.files import dumps_strict
from mvtex.util.output import writer
from mvtex.util.parallel import ThreadState, check_backend, configure_threads, map_unordered
from mvtex.views.cameras import check_weights, interpolate_camera
from mvtex.views.synthesizer import ViewOptions, ViewSynthesizer

_WRITE_BLOCK = 32  # poses computed between two writes of the output arrays


@dataclass(frozen=True)
class _ViewSpec:
    """What a worker needs to compute views (picklable): paths, not open files."""

    dataset: str
    rig: Rig
    texcoords: str
    options: ViewOptions
    cameras: tuple
    weights: tuple
    key: str  # one run: a worker keeps its synthesizer between the run's tasks


_VIEW_STATE = ThreadState()  # each thread's synthesizer for the run it serves


def _view_state(spec: _ViewSpec) -> "ViewSynthesizer":
    """A worker's synthesizer for a run."""

    configure_threads(1)
    ds = load_dataset(spec.dataset, validate=False)
    return ViewSynthesizer(ds, spec.rig, open_texcoords(spec.texcoords, ds.num_vertices), spec.options)


def _views_of_poses(synth: "ViewSynthesizer", cameras: Sequence[Camera], weights: Sequence[Mapping[str, float]],
                    poses: Sequence[int], tick=None) -> tuple[dict, dict]:
    """Every view of `poses`: ({name: (p,n',2) float32}, {name: (p,n') bool}); `tick()`
    (when given) after each view, for a progress bar that moves inside a block."""
    n_sub = len(synth.texcoords.uv)
    disp = {c.name: np.empty((len(poses), n_sub, 2), np.float32) for c in cameras}
    asg = {c.name: np.empty((len(poses), n_sub), bool) for c in cameras}
    for row, pose in enumerate(poses):
        state = synth.prepare(pose)
        for cam, w in zip(cameras, weights):
            disp[cam.name][row], asg[cam.name][row] = synth.view(state, cam, w)
            if tick is not None:
                tick()
    return disp, asg


def _view_block(spec: _ViewSpec, start: int, poses: list[int]):
    """In a worker: the views of one block of poses; returns (start, disp, asg)."""
    synth = _VIEW_STATE.get(spec.key, lambda: _view_state(spec))
    return (start, *_views_of_poses(synth, spec.cameras, spec.weights, poses))


@dataclass(frozen=True)
class NovelViews:
    """What `novel_views` made.

    Attributes:
        out: the texcoord set of the views (its cameras in out/rig.yaml).
        method: "blend" or "reconstruct".
        views: view name -> its weights over the array's cameras.
        poses: dataset pose indices, the set's rows.
        cameras: view name -> its camera centre (world, m).
        measured: with `--plot`, the views measured against gt (`mvtex.views.measure.path_plot`).
    """

    out: Path
    method: str
    views: dict[str, dict[str, float]]
    poses: list[int]
    cameras: dict[str, list[float]]
    measured: dict | None = None

    def to_json(self) -> dict:
        out = {"out": str(self.out), "method": self.method, "views": self.views, "poses": self.poses,
               "cameras": self.cameras}
        if self.measured is not None:
            out["measured"] = self.measured
        return out


@writer("views", inputs=lambda a: (a["dataset"], a["texcoords"], a["rig"]))
def novel_views(dataset, rig: Rig, texcoords, out: str | os.PathLike, weights: Sequence[Mapping[str, float]],
                names: Sequence[str], *, poses: Sequence[int] | None = None, options: ViewOptions = ViewOptions(),
                progress: bool = True, workers: int = 1,
                scheduler: str | None = None, overwrite: bool = False) -> NovelViews:
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
        workers: local worker processes (1: this process), see `mvtex.util.parallel.map_unordered`.
        scheduler: Dask scheduler address (overrides `workers`). Workers compute blocks of
            `_WRITE_BLOCK` poses; the result does not depend on where they ran.

    Returns:
        A `NovelViews`; `.to_json()` is the JSON of `mvtex views --json`.
    """

    dataset = as_dataset(dataset)
    rig = as_rig(rig)
    texcoords = as_texcoords(texcoords)
    out = as_path(out, "out")
    poses = None if poses is None else as_indices(poses, "poses")
    check_instance(options, ViewOptions, "options")
    if isinstance(weights, (str, bytes, dict)) or not hasattr(weights, "__iter__"):
        raise OptionError("weights", f"must be a list of camera -> weight mappings, got {type(weights).__name__}")
    if isinstance(names, (str, bytes)) or not hasattr(names, "__iter__"):
        raise OptionError("names", f"must be a list of view names, got {type(names).__name__}")
    weights, names = list(weights), list(names)

    check_backend(workers, scheduler)
    if len(weights) != len(names) or not names:
        raise OptionError("names", "must hold one name per view")
    if len(set(names)) != len(names):
        raise OptionError("names", f"must be unique, got {list(names)}")
    for name in names:  # they become folder names
        try:
            check_camera_name(name)
        except ValueError as err:
            raise OptionError("names", f"holds a name that is not allowed: {err}") from None
    weights = [check_weights(w, rig) for w in weights]
    synth = ViewSynthesizer(dataset, rig, texcoords, options)
    for w in weights:
        absent = [c for c in w if c not in texcoords.cameras]
        if absent:
            raise InputError(texcoords.path, f"no texcoords for camera {', '.join(absent)} in this set "
                             f"(it has {', '.join(texcoords.cameras)})")
    cameras = [interpolate_camera(rig, w, name) for w, name in zip(weights, names)]
    poses = texcoords.poses if poses is None else [int(p) for p in poses]
    check_outside_body(rig, dataset, poses)
    check_outside_body(Rig(tuple(cameras), "the novel views"), dataset, poses)
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
              "dataset": dataset_record(dataset), "rig": rig_record(Rig(tuple(cameras))),
              "inputs": {"texcoords": {c: texcoords.fingerprint(c) for c in synth.array},
                         "array": rig_record(rig.select(synth.array))}}
    record = json.loads(dumps_strict(record))  # as texcoords.json holds it (lists, not tuples)
    with synth:
        partial = PartialSet(out, "views", "views-", faces=texcoords.faces, uv=texcoords.uv, parent=texcoords.parent,
                             source=f"views-{options.method}", subdiv=texcoords.subdiv, poses=poses,
                             cameras=list(names), record=record)

        def write(start: int, disp: dict, asg: dict, counted: bool = False) -> None:
            rows = range(start, start + len(next(iter(asg.values()))))
            for name in names:
                partial.write(name, rows, disp[name], asg[name])
            if not counted:
                bar.update(len(rows) * len(names))

        size = _WRITE_BLOCK
        if workers > 1 or scheduler:  # blocks small enough that every worker gets several
            size = max(1, min(_WRITE_BLOCK, -(-len(poses) // (4 * max(workers, 2)))))
        done = np.logical_and.reduce([partial.done[name] for name in names])
        starts = [start for start in range(0, len(poses), size) if not done[start:start + size].all()]
        bar = tqdm(total=len(poses) * len(names), initial=int(done.sum()) * len(names),
                   desc=f"views ({options.method})", unit="view", disable=not progress, file=sys.stderr)
        if workers <= 1 and not scheduler:
            for start in starts:  # the bar moves view by view
                write(start, *_views_of_poses(synth, cameras, weights, poses[start:start + size],
                                              tick=lambda: bar.update(1)), counted=True)
        else:

            spec = _ViewSpec(dataset=str(Path(dataset.path).resolve()), rig=rig,
                             texcoords=str(Path(texcoords.path).resolve()), options=options,
                             cameras=tuple(cameras),
                             weights=tuple(dict(w) for w in weights), key=uuid.uuid4().hex)
            tasks = [(spec, start, poses[start:start + size]) for start in starts]
            for start, disp, asg in map_unordered(_view_block, tasks, workers=workers, scheduler=scheduler):
                write(start, disp, asg)
        bar.close()
    save_rig(Rig(tuple(cameras)), partial.path / "rig.yaml", overwrite=True)  # the unfinished set is mvtex's
    partial.finish()
    return NovelViews(out=out, method=options.method, views=record["views"], poses=poses,
                      cameras={c.name: c.center.tolist() for c in cameras})
