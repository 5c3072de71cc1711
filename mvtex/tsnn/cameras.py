"""One model per camera, trained side by side on local processes or a Dask cluster,
resumable (a model trained from the same inputs is kept).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Sequence

from tqdm import tqdm

from mvtex.data.dataset import as_dataset, load_dataset
from mvtex.data.rig import load_rig
from mvtex.data.texcoords import as_texcoords, open_texcoords, recorded_rig
from mvtex.tsnn.config import training_rig
from mvtex.tsnn.modeldir import TrainedCameras, TrainResult, _kept_model
from mvtex.tsnn.train import TrainOptions, _inputs_key, _resolve, _split, dataset_fingerprint, train
from mvtex.util.checks import as_list, as_path, check_instance
from mvtex.util.errors import InputError, OptionError
from mvtex.util.output import writer
from mvtex.util.parallel import check_backend, configure_threads, map_unordered


def _train_camera_task(dataset: str, texcoords: str, camera: str, out: str, options: TrainOptions) -> TrainResult:
    """In a worker: one camera's model from paths (torch on one thread: the workers already
    fill the cores)."""

    configure_threads(1)
    ds = load_dataset(dataset, validate=False)
    return train(ds, open_texcoords(texcoords, ds.num_vertices), out, camera=camera, options=options, progress=False)


@writer("train", in_place=True, inputs=lambda a: (a["dataset"], a["texcoords"]))
def train_cameras(dataset, texcoords, cameras: Sequence[str], out: str | os.PathLike,
                  options: TrainOptions = TrainOptions(), *, workers: int = 1, scheduler: str | None = None,
                  progress: bool = True, overwrite: bool = False) -> TrainedCameras:
    """One model per camera, OUT/<camera>/ (each a model directory as `train` writes it),
    trained side by side on local processes or a Dask cluster (`mvtex.util.parallel`).

    Each model is `train` with that camera, written atomically. A rerun keeps the model of
    every camera whose config.json records the inputs it would be trained from now (see
    `_inputs_key`), so an interrupted run continues with the cameras it had not finished,
    and trains the others again. On workers torch runs one thread per process (the workers
    fill the cores), which can change a network's last bits against a multi-threaded run,
    not a `gp` model's (tested bit for bit).

    Returns:
        A `mvtex.tsnn.modeldir.TrainedCameras` (models: camera -> its `TrainResult`).
    """

    dataset = as_dataset(dataset)
    texcoords = as_texcoords(texcoords)
    out = as_path(out, "out")
    check_instance(options, TrainOptions, "options")
    if isinstance(cameras, (str, bytes)) or not hasattr(cameras, "__iter__") \
            or not all(isinstance(c, str) for c in cameras) or not list(cameras):
        raise OptionError("cameras", f"must be a non-empty list of camera names, got {cameras!r:.60}")

    out = Path(out)
    check_backend(workers, scheduler)
    cameras = list(cameras)
    missing = [c for c in cameras if c not in texcoords.cameras]
    if missing:
        raise InputError(texcoords.path, f"no camera {missing[0]!r} in this texcoord set "
                         f"(it has {', '.join(texcoords.cameras)})")
    if len(set(cameras)) != len(cameras):
        raise OptionError("cameras", f"lists a camera twice: {', '.join(cameras)}")
    texcoords.check_dataset(dataset)
    for c in cameras if texcoords.poses else []:  # reading a row checks the camera's whole arrays
        texcoords.displacement(c, texcoords.poses[0])
    resolved = _resolve(options, cameras[0])
    split = _split(dataset, texcoords)
    dataset_hash = None
    models: dict[str, TrainResult] = {}
    for c in cameras:
        if not (out / c / "config.json").is_file():
            continue
        if dataset_hash is None:
            dataset_hash = dataset_fingerprint(dataset)
        kept = _kept_model(out / c, _inputs_key(dataset, texcoords, [c], {}, split, resolved, dataset_hash,
                                                rig=training_rig(None, texcoords, [c])))
        if kept is not None:
            models[c] = kept
            if progress:
                print(f"{out / c}: trained before from the same inputs; kept", file=sys.stderr)
    todo = [c for c in cameras if c not in models]
    tasks = [(str(Path(dataset.path).resolve()), str(Path(texcoords.path).resolve()), c, str(out / c), options)
             for c in todo]
    if workers <= 1 and not scheduler:
        for c in todo:
            models[c] = train(dataset, texcoords, out / c, camera=c, options=options, progress=progress)
    else:

        with tqdm(total=len(cameras), initial=len(cameras) - len(todo), desc="train", unit="camera",
                  disable=not progress, file=sys.stderr) as bar:
            for summary in map_unordered(_train_camera_task, tasks, workers=workers, scheduler=scheduler):
                models[summary.camera] = summary
                bar.update(1)
    arch = {m.arch for m in models.values()}
    return TrainedCameras(out=str(out), cameras=cameras, arch=arch.pop() if len(arch) == 1 else sorted(arch),
                          models={c: models[c] for c in cameras}, kept=[c for c in cameras if c not in todo])


def train_models(dataset, texcoords, out: str | os.PathLike, cameras: Sequence[str] | None = None, *, rig=None,
                 options: TrainOptions = TrainOptions(), workers: int = 1, scheduler: str | None = None,
                 progress: bool = True, overwrite: bool = False) -> TrainResult | TrainedCameras:
    """`mvtex train`: the models a texcoord set's cameras need, by how many are named.

    - one camera: its model in `out` (`train` with `camera`; `gp` by default), which records
      the camera from `rig` where given, else from the texcoord set's record of it;
    - several cameras: one model each in OUT/<camera>, side by side on `workers` or a Dask
      `scheduler` (`train_cameras`);
    - None: one network for every camera of the set, conditioned on the camera (`unet`),
      which needs the set's rig: `rig`, else the rig the set records (TC/rig.yaml).

    Raises:
        OptionError: an empty camera list; `workers` above 1 or a `scheduler` with fewer
            than two cameras; no rig for a network of every camera.
    """

    texcoords = as_texcoords(texcoords)
    names = None if cameras is None else as_list(cameras, "cameras", str, "camera names")
    if names is not None and not names:
        raise OptionError("cameras", "needs a camera name or a list of them, got none")
    if (workers not in (None, 1) or scheduler is not None) and (names is None or len(names) < 2):
        raise OptionError("workers", "above 1 and a scheduler train several cameras side by side: name two or "
                          "more cameras")
    if names is not None and len(names) > 1:
        return train_cameras(dataset, texcoords, names, out, options, workers=workers or 1, scheduler=scheduler,
                             progress=progress, overwrite=overwrite)
    if names is not None:  # the model records its camera from `rig`, else from the set's record of it
        return train(dataset, texcoords, out, camera=names[0], rig=rig, options=options, progress=progress,
                     overwrite=overwrite)
    if rig is None:
        recorded = recorded_rig(texcoords.path)
        if recorded is None:
            raise OptionError("rig", "is needed for one network of every camera (the texcoord set records no rig); "
                              "or name a camera for its own model")
        rig = load_rig(recorded)
    return train(dataset, texcoords, out, rig=rig, options=options, progress=progress, overwrite=overwrite)
