"""Training a texture sliding network on a texcoord set: one camera's, or one for every
camera of the set, conditioned on the camera.

The targets are the texcoord set's per-vertex displacements d (on its possibly subdivided
mesh); the network's image is read at every vertex's T_G with bilinear sampling and the
loss is the (optionally weighted) mean squared error of d over vertices and samples
(DESIGN §5 TSNN). A sample is a (pose, camera) pair. Adam at lr 1e-3, the dataset's
train/val/test split restricted to the poses of the texcoord set, early stopping on the
validation loss.

Architectures (`TrainOptions.arch`): `gp` (the default with a camera name) models the
principal components of the camera's d as Gaussian processes of the pose
(`mvtex.tsnn.gp`): the most accurate from a few hundred poses up to the ~1,000 measured.
`unet` (the default without a camera name) reads geometry images of the inferred mesh
(`mvtex.tsnn.geometry`) and the pose; trained without a camera name it also reads the view
of every texel from the sample's camera, which is what lets it serve cameras it never saw.
`paper` is the paper's pose -> fully connected -> transposed convolutions decoder (one
camera only).
`mlp` (one camera) predicts the same principal components as `gp` with an ensemble of
small MLPs of the pose (`mvtex.tsnn.mlp`): O(K) per epoch, and its members' spread is a
predictive uncertainty.

A model directory holds:

    model.safetensors   the state dict (weights, normalisation buffers)
    config.json         `mvtex.tsnn.config.ModelConfig`: the camera (null: conditioned on the
                        camera), the training cameras whole ("rig"), the architecture, the
                        mesh it serves, the inputs' fingerprint and the training record
    geometry.npz        `unet`: the reference of its geometry images (rest edge lengths,
                        seam groups), so that it serves every set of its garment
    loss.png            training and validation loss per epoch (networks)
    relevance.png       which pose coordinates move which principal component of d (gp)
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Sequence

import numpy as np
from tqdm import tqdm

from mvtex.data.dataset import as_dataset
from mvtex.data.rig import as_rig
from mvtex.data.texcoords import as_texcoords
from mvtex.tsnn.atlas import AtlasSampler
from mvtex.tsnn.config import (
    GEOMETRY_FILE,
    MODEL_VERSION,
    MeshRecord,
    ModelConfig,
    camera_record,
    mesh_fingerprint,
    training_rig,
)
from mvtex.tsnn.geometry import NUM_CHANNELS, MeshGeometry, geometry_images
from mvtex.tsnn.gp import MAX_TRAIN, fit_pose_gp
from mvtex.tsnn.mlp import fit_pose_mlp
from mvtex.tsnn.model import TSNN, PaperConfig, UNet, UNetConfig
from mvtex.tsnn.modeldir import TrainResult, _write_model, rebuild_mesh
from mvtex.tsnn.options import TrainOptions
from mvtex.tsnn.pca import evenly_spaced
from mvtex.tsnn.samples import DisplacementRows, Forward, Samples, sample_losses, weighted_mse
from mvtex.util.checks import as_path, check_instance
from mvtex.util.errors import InputError, OptionError
from mvtex.util.fingerprint import fingerprint, fingerprint_record
from mvtex.util.output import writer
from mvtex.util.progress import step_bar

__all__ = ["TrainOptions", "dataset_fingerprint", "resolve_options", "train", "train_camera"]


def resolve_device(device: str) -> str:
    """The device that runs `device` ("auto": CUDA when available, else the CPU).

    Raises:
        OptionError: CUDA requested but not available.
    """
    import torch  # noqa: PLC0415 (loaded on use)

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise OptionError("device", f"{device!r} requested but CUDA is not available")
    return device


def resolve_options(options: TrainOptions) -> TrainOptions:
    """`options` with device, resolution, widths and the other automatic values filled in for
    the device that runs them."""
    device = resolve_device(options.device)
    gpu = device.startswith("cuda")

    def given(value, default):
        return default if value is None else value

    return replace(options, device=device,
                   resolution=given(options.resolution, (512 if options.arch == "paper" else 256) if gpu else 64),
                   widths=tuple(options.widths) if options.widths else (8, 16, 32, 64),
                   batch_size=given(options.batch_size, 16 if options.arch == "paper" else 8),
                   width=given(options.width, 128 if options.arch == "mlp" else 256),
                   min_width=given(options.min_width, 16 if gpu else 8),
                   deterministic=(not gpu) if options.deterministic is None else options.deterministic)


def _check_texcoord_mesh(dataset, texcoords) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    faces, uv, parent = rebuild_mesh(dataset.faces, dataset.uv, texcoords.subdiv)
    same = (texcoords.faces.shape == faces.shape and np.array_equal(texcoords.faces, faces)
            and np.array_equal(texcoords.parent, parent) and texcoords.uv.shape == uv.shape
            and np.allclose(texcoords.uv, uv, rtol=0, atol=1e-6))
    if not same:
        raise InputError(texcoords.path / "mesh.npz", f"is not the dataset mesh subdivided {texcoords.subdiv} "
                         "time(s) (faces, parent or uv differ), so a prediction could not rebuild it")
    return faces, uv, parent


def _split(dataset, texcoords) -> dict[str, list[int]]:
    present = set(texcoords.poses)
    split = {k: [int(p) for p in dataset.split[k] if int(p) in present] for k in ("train", "val", "test")}
    if not split["train"]:
        raise InputError(texcoords.path / "texcoords.json", "holds none of the dataset's training poses "
                         f"({len(dataset.split['train'])} in the split of {dataset.path})")
    if not split["val"]:  # early stopping and the choice of the best epoch need it
        raise InputError(texcoords.path / "texcoords.json", "holds none of the dataset's validation poses "
                         f"({len(dataset.split['val'])} in the split of {dataset.path}); slide them too, or "
                         "give the dataset a split.json with a non-empty 'val'")
    return split


def train_camera(dataset, texcoords, camera: str, out: str | os.PathLike, options: TrainOptions = TrainOptions(),
                 progress: bool = True) -> TrainResult:
    """Train the texture sliding network of one camera (`train` with a camera name)."""
    return train(dataset, texcoords, out, camera=camera, options=options, progress=progress)


def _resolve(options: TrainOptions, camera: str | None) -> TrainOptions:
    """The options `train` runs with: the default architecture for a camera (`gp`) or for
    every camera (`unet`), then `TrainOptions.resolved`; ValueError if invalid."""
    if options.arch is None:
        options = replace(options, arch="gp" if camera is not None else "unet")
    options = resolve_options(options)
    return options


def dataset_fingerprint(dataset) -> str:
    """What a model depends on of the dataset: its inferred shapes, poses, mesh and body."""

    return fingerprint(dataset.inferred, dataset.poses, dataset.faces, dataset.uv, *dataset.body_arrays())


def _inputs_key(dataset, texcoords, cameras: Sequence[str], views: dict, split: dict, options: TrainOptions,
                dataset_hash: str | None = None, rig=None) -> str:
    """Content fingerprint of everything a model is trained from: the dataset's inferred
    shapes, poses and mesh (and its body, when it has one), the texcoord set's mesh, poses
    and the cameras' arrays, the split, the cameras' views, the cameras whole (`rig`, what
    config.json records of them, `training_rig`) and the resolved options.
    config.json records it as "inputs"; `train_cameras` keeps a camera's model that records
    the key it would train with (the same inputs train the same model: bit for bit for `gp`)."""

    record = {
        "version": MODEL_VERSION,
        "dataset": dataset_hash or dataset_fingerprint(dataset),
        "texcoords": {"mesh": fingerprint(texcoords.faces, texcoords.uv, texcoords.parent), "poses": texcoords.poses,
                      "cameras": {c: texcoords.fingerprint(c) for c in cameras}},
        "views": views, "split": split, "options": asdict(options),
        "rig": None if rig is None else {cam.name: camera_record(cam) for cam in rig},
    }
    return fingerprint_record(record)


@writer("train", inputs=lambda a: (a["dataset"], a["texcoords"]))
def train(dataset, texcoords, out: str | os.PathLike, *, camera: str | None = None, rig=None,
          options: TrainOptions = TrainOptions(), train_poses: Sequence[int] | None = None,
          cameras: Sequence[str] | None = None, progress: bool = True, overwrite: bool = False) -> TrainResult:
    """Train a texture sliding network and write a model directory.

    Args:
        dataset: the `mvtex.data.dataset.Dataset` the texcoord set was made from (poses, split, mesh).
        texcoords: an opened `TexcoordSet`.
        out: model directory to write (replaced atomically).
        camera: train one camera's network; None: one network on every camera of the set,
            conditioned on the camera (`unet` only; needs `rig`).
        rig: a `mvtex.data.rig.Rig` holding the set's cameras (their extrinsics are the
            network's view inputs); needed when `camera` is None. config.json records the
            training cameras whole (`predict` without a rig records them as the set's rig):
            from `rig`, else from the texcoord set's record of them.
        options: see `TrainOptions`.
        train_poses: train on these poses of the training split only (learning curves);
            None: every training pose of the set.
        cameras: with `camera` None, train on these cameras of the set only (held-out
            camera experiments); None: all of them.
        progress: show a progress bar with the losses on stderr.
        overwrite: replace another command's output at `out` (never files mvtex did not
            write, never an input: the writer policy of `mvtex.util.output`).

    Returns:
        A JSON-serialisable summary: camera, cameras, arch, out, device, epochs_run,
        best_epoch, seconds, gain (None: off), losses {"train"|"val"|"test": {"loss", "rmse",
        "zero_loss", "gain", "gain_loss"}} (before the gain),
        split sizes (poses).

    Raises:
        InputError: a camera or pose missing from the texcoord set or the rig, a texcoord
            mesh that is not the dataset mesh subdivided, overlapping uv charts.
        OptionError: bad options (`paper` without a camera name).
    """

    dataset = as_dataset(dataset)
    texcoords = as_texcoords(texcoords)
    out = as_path(out, "out")
    rig = None if rig is None else as_rig(rig)
    check_instance(options, TrainOptions, "options")
    if camera is not None and not isinstance(camera, str):
        raise OptionError("camera", f"must be a camera name or None, got {type(camera).__name__}")
    import torch  # noqa: PLC0415 (loaded on use)

    out = Path(out)
    options = _resolve(options, camera)
    if camera is not None:
        if camera not in texcoords.cameras:
            raise InputError(texcoords.path, f"no camera {camera!r} in this texcoord set "
                             f"(it has {', '.join(texcoords.cameras)})")
        cameras = [camera]
    else:
        if options.arch in ("paper", "gp", "mlp"):
            raise OptionError("arch", f"{options.arch} maps the pose alone: train it per camera (give a camera name)")
        if rig is None:
            raise OptionError("rig", "is needed for a network of every camera: the rig the texcoord set was made with")
        cameras = list(texcoords.cameras) if cameras is None else [str(c) for c in cameras]
        absent = [c for c in cameras if c not in texcoords.cameras]
        if absent or not cameras:
            raise InputError(texcoords.path, f"cameras {', '.join(absent) or '(none)'} are not in this texcoord set "
                             f"(it has {', '.join(texcoords.cameras)})")
        missing = [c for c in cameras if c not in rig.names]
        if missing:
            raise InputError(texcoords.path, f"cameras {', '.join(missing)} of the texcoord set are not in the rig "
                             f"(it has {', '.join(rig.names)})")
    views = {c: rig[c].cam_from_world.tolist() for c in cameras} if rig is not None and camera is None else {}
    cameras_whole = training_rig(rig, texcoords, cameras)
    texcoords.check_dataset(dataset)
    faces, uv, parent = _check_texcoord_mesh(dataset, texcoords)
    split = _split(dataset, texcoords)
    if train_poses is not None:
        keep = {int(p) for p in train_poses}
        split["train"] = [p for p in split["train"] if p in keep]
        if not split["train"]:
            raise OptionError("train_poses", "holds no training pose of the texcoord set")
    device = torch.device(options.device)
    t0 = time.perf_counter()
    reference = MeshGeometry.of_dataset(dataset) if options.arch == "unet" else None

    previous_deterministic = torch.are_deterministic_algorithms_enabled()
    try:
        torch.use_deterministic_algorithms(bool(options.deterministic))
        with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
            torch.manual_seed(options.seed)
            if options.arch == "gp":
                result = _train_gp(dataset, texcoords, cameras[0], split, options, device, progress)
            elif options.arch == "mlp":
                result = _train_mlp(dataset, texcoords, cameras[0], split, options, progress)
            else:
                result = _train(dataset, texcoords, cameras, views, faces, uv, parent, split, options, device,
                                progress, reference)
    finally:
        torch.use_deterministic_algorithms(previous_deterministic)
    model, config, history, best_epoch, losses = result
    seconds = time.perf_counter() - t0
    gain = validation_gain(options, dataset, losses)

    record = ModelConfig(
        camera=camera, version=MODEL_VERSION,
        inputs=_inputs_key(dataset, texcoords, cameras, views, split, options, rig=cameras_whole), gain=gain,
        cameras={c: np.asarray(v) for c, v in views.items()} or {camera: None}, rig=cameras_whole,
        architecture=config.to_dict(),
        pose_normalisation={"mean": model.pose_mean.cpu().tolist(), "std": model.pose_std.cpu().tolist()},
        output_scale=float(model.output_scale),
        mesh=MeshRecord(subdiv=texcoords.subdiv, num_base_vertices=int(dataset.num_vertices),
                        num_vertices=int(len(uv)), num_faces=int(len(faces)),
                        base_mesh=mesh_fingerprint(dataset.faces, dataset.uv)),
        atlas={"convention": "texel (r, c) centre at (u, v) = ((c+0.5)/R, (r+0.5)/R); row 0 at v=0",
               "dilation": options.dilation},
        geometry=None if reference is None else {"file": GEOMETRY_FILE},
        dataset={"path": str(dataset.path), "name": dataset.name},
        texcoords={"path": str(texcoords.path), "source": texcoords.source, "subdiv": texcoords.subdiv},
        split=split, options=asdict(options), device=str(device), torch_version=torch.__version__,
        epochs_run=len(history["train"]), best_epoch=best_epoch, seconds=round(seconds, 2), losses=losses,
        history=history)
    _write_model(out, model, record, None if reference is None else reference.reference_arrays())
    return TrainResult(camera=camera, cameras=list(cameras), arch=options.arch, out=str(out), device=str(device),
                       resolution=getattr(config, "resolution", None), epochs_run=record.epochs_run,
                       best_epoch=best_epoch, seconds=record.seconds, num_poses={k: len(v) for k, v in split.items()},
                       losses=losses, gain=gain)


def validation_gain(options: TrainOptions, dataset, losses: dict) -> float | None:
    """The gain config.json records (`TrainOptions.gain`): the validation poses' least-squares
    gain clipped to [0, 1], or None (off: predictions are used as they are). Its default is
    on for a corrected set."""
    on = dataset.correction is not None if options.gain is None else options.gain
    if not on or "val" not in losses:
        return None
    return float(min(max(losses["val"]["gain"], 0.0), 1.0))


def _masked_stats(images: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel mean and std of (K,C,R,R) images over the texels of a (R,R) mask."""
    values = images[:, :, mask].transpose(1, 0, 2).reshape(images.shape[1], -1).astype(np.float64)
    return values.mean(1), values.std(1)


def _build(options: TrainOptions, sampler, train: Samples, views: dict, pose_dim: int, geometry_train):
    """The network with its normalisation set from the training samples."""
    import torch  # noqa: PLC0415 (loaded on use)

    mean_d = train.d_numpy.mean(axis=0)  # (n',2): the pose-independent part of d
    scale = float(np.sqrt(np.mean((train.d_numpy - mean_d) ** 2))) if len(train) > 1 else 0.0
    scale = max(scale, 1e-4)  # uv units; keeps a constant target from dividing by zero
    x_train = train.x.cpu().numpy()
    if options.arch == "paper":
        config = PaperConfig(pose_dim=pose_dim, resolution=options.resolution, width=options.width,
                             min_width=options.min_width, dropout=options.dropout)
        model = TSNN(config)
        model.set_normalisation(x_train.mean(0), x_train.std(0), scale)
    else:

        config = UNetConfig(pose_dim=pose_dim, resolution=options.resolution, geometry_channels=NUM_CHANNELS,
                            view=bool(views), widths=tuple(options.widths))
        model = UNet(config)
        region = sampler.layout.tri_id >= 0  # charts and their dilated rings
        r = options.resolution
        centres = (np.arange(r) + 0.5) / r
        atlas = np.stack([region.astype(np.float32), *np.meshgrid(centres, centres)])  # mask, u (columns), v (rows)
        g_mean, g_std = _masked_stats(geometry_train, sampler.layout.covered)
        v_mean = v_std = None
        if views:
            cams = torch.tensor([views[c] for c in views], dtype=torch.float32)
            rng = np.random.default_rng(0)
            pick = rng.choice(len(train), size=min(len(train), 256), replace=False)
            rows = train.pose_row.cpu().numpy()[pick]
            with torch.no_grad():
                v = UNet.view_features(torch.from_numpy(geometry_train[rows]),
                                       cams[train.camera.cpu().numpy()[pick]]).numpy()
            v_mean, v_std = _masked_stats(v, sampler.layout.covered)
        model.set_normalisation(pose_mean=x_train.mean(0), pose_std=x_train.std(0), geometry_mean=g_mean,
                                geometry_std=g_std, view_mean=v_mean, view_std=v_std, atlas=atlas,
                                output_scale=scale)
    with torch.no_grad():
        bias = sampler.to_image(mean_d / scale)  # (R,R,2), row 0 at v = 0
        model.bias.copy_(torch.from_numpy(bias).permute(2, 0, 1)[None])
    return model, config


def _train(dataset, texcoords, cameras, views, faces, uv, parent, split, options: TrainOptions, device, progress,
           reference=None):
    import torch  # noqa: PLC0415 (loaded on use)

    sampler = AtlasSampler(faces, uv, options.resolution, dilation=options.dilation, source=texcoords.path / "mesh.npz")
    grid = sampler.grid().to(device)
    geometry = {k: None for k in split}
    if options.arch == "unet":

        geometry = {k: geometry_images(dataset, split[k], sampler, parent, geometry=reference) for k in split}
    data = {k: Samples(dataset, texcoords, cameras, split[k], options.weight_assigned, device, geometry[k])
            for k in split}
    train = data["train"]
    monitor = "val" if len(data["val"]) else "train"
    model, config = _build(options, sampler, train, views, int(dataset.poses.shape[1]), geometry["train"])
    model.to(device)
    cams = torch.tensor([views[c] for c in cameras], dtype=torch.float32, device=device) if views else None
    forward = Forward(model, cams)

    def vertices(data: Samples, idx):
        return sampler.sample(forward(data, idx), grid)

    optimiser = torch.optim.AdamW(model.parameters(), lr=options.lr, weight_decay=options.weight_decay)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, T_max=options.epochs,
                                                          eta_min=options.lr * options.lr_min_factor)
    generator = torch.Generator().manual_seed(options.seed)
    history: dict[str, list[float]] = {"train": [], "val": []}
    best = (math.inf, 0, None)
    label = cameras[0] if len(cameras) == 1 and not views else f"{len(cameras)} cameras"
    bar = tqdm(range(1, options.epochs + 1), desc=f"train {label}", unit="epoch", disable=not progress, leave=True)
    for epoch in bar:
        model.train()
        order = torch.randperm(len(train), generator=generator).to(device)
        total = 0.0
        # Drop a last batch of one: batch norm cannot normalise a single sample's 1 value/channel
        # statistics reliably (and the fc stage would see one sample).
        starts = [s for s in range(0, len(train), options.batch_size)
                  if len(train) - s > 1 or len(train) == 1]
        for start in starts:
            idx = order[start:start + options.batch_size]
            x = train.x[idx]
            if options.pose_noise > 0:
                # Jitter in units of each component's training std (the network's normalised input).
                noise = torch.randn(x.shape, generator=generator).to(device)
                x = x + options.pose_noise * model.pose_std * noise
            pred = sampler.sample(forward(train, idx, x), grid)
            loss = weighted_mse(pred, train.d[idx], train.w[idx])
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            total += float(loss.detach()) * len(idx)
        schedule.step()
        history["train"].append(total / max(1, sum(len(order[s:s + options.batch_size]) for s in starts)))
        if monitor == "val":
            model.eval()
            history["val"].append(sample_losses(vertices, data["val"], 64)["loss"])
        score = history[monitor][-1]
        if score < best[0]:
            best = (score, epoch, {k: v.detach().clone() for k, v in model.state_dict().items()})
        bar.set_postfix(train=f"{history['train'][-1]:.3g}", val=f"{history['val'][-1]:.3g}" if history["val"] else "-",
                        best=best[1])
        if epoch - best[1] >= options.patience:
            break
    bar.close()
    if best[2] is not None:
        model.load_state_dict(best[2])
    model.eval()
    losses = {k: sample_losses(vertices, v, 64) for k, v in data.items() if len(v)}
    return model.cpu(), config, history, best[1], losses


def _train_gp(dataset, texcoords, camera: str, split, options: TrainOptions, device, progress):
    """`gp`: fit the Gaussian processes of one camera (float64, on `device`; the model comes
    back on the CPU); `_train`'s results. Every training pose is used (above `MAX_TRAIN`
    by the inducing-pose posterior); the training losses are those of at most `MAX_TRAIN`
    evenly spaced training poses."""

    train_poses = split["train"]
    pose_vectors = np.asarray(dataset.poses[train_poses], dtype=np.float32).reshape(len(train_poses), -1)
    bar, advance = step_bar(f"train {camera} (gp, {len(train_poses)} poses)", progress)

    model = fit_pose_gp(pose_vectors, DisplacementRows(texcoords, camera, train_poses), components=options.components,
                        progress=advance, device=device)
    bar.close()
    scored = dict(split, train=[train_poses[i] for i in evenly_spaced(len(train_poses), MAX_TRAIN)])
    data = {k: Samples(dataset, texcoords, [camera], scored[k], options.weight_assigned, "cpu") for k in scored}

    def vertices(data: Samples, idx):
        return model(data.x[idx])

    losses = {k: sample_losses(vertices, v, 256) for k, v in data.items() if len(v)}
    return model, model.config, {"train": [], "val": []}, 0, losses


def _train_mlp(dataset, texcoords, camera: str, split, options: TrainOptions, progress):
    """`mlp`: fit an ensemble of MLPs on the principal components of one camera's d (on the
    CPU, float32), each member's epoch chosen on the validation poses; `_train`'s results.
    The training losses are those of at most `MAX_TRAIN` evenly spaced training poses."""

    train_poses = split["train"]
    pose_vectors = np.asarray(dataset.poses[train_poses], dtype=np.float32).reshape(len(train_poses), -1)
    val = Samples(dataset, texcoords, [camera], split["val"], options.weight_assigned, "cpu")
    bar, advance = step_bar(f"train {camera} (mlp, {len(train_poses)} poses)", progress)

    model, history = fit_pose_mlp(pose_vectors, DisplacementRows(texcoords, camera, train_poses), val.x.numpy(), val.d_numpy,
                                  components=options.components, hidden=options.width, members=options.members,
                                  seed=options.seed, lr=options.lr, progress=advance)
    bar.close()
    scored = dict(split, train=[train_poses[i] for i in evenly_spaced(len(train_poses), MAX_TRAIN)])
    data = {k: (val if k == "val" else Samples(dataset, texcoords, [camera], scored[k], options.weight_assigned, "cpu"))
            for k in scored}

    def vertices(data: Samples, idx):
        return model(data.x[idx])

    losses = {k: sample_losses(vertices, v, 256) for k, v in data.items() if len(v)}
    best = history.pop("best_epoch")
    return model, model.config, history, max(best), losses
