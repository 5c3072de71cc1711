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
    config.json         {"format": "mvtex-tsnn", "version": 2, "camera" (null: conditioned
                         on the camera), "cameras" (name -> cam_from_world of the training
                         cameras), "architecture", "mesh" (subdiv, vertex counts, base-mesh
                         hash), "atlas", "split", "options", "losses", "history",
                         "inputs" (content fingerprint of what it was trained from), ...}
    loss.png            training and validation loss per epoch (networks)
    relevance.png       which pose coordinates move which principal component of d (gp)
"""

from __future__ import annotations

import math
import os
import re
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from mvtex.tsnn.modeldir import (MODEL_FORMAT, MODEL_VERSION, TrainResult, _write_model, mesh_fingerprint,
                                 rebuild_mesh)
from mvtex.util.checks import check_field_types, check_seed
from mvtex.util.errors import InputError, OptionError
from mvtex.util.output import writer

ARCHS = ("gp", "mlp", "unet", "paper")


MAX_RESOLUTION = 2048  # atlas image size: 2·R² floats per pose and per batch item


MAX_WIDTH = 1024  # channels of the first stage


MAX_SUBDIV = 3
_DEVICE = re.compile(r"^(auto|cpu|mps|cuda(:\d{1,3})?)$")


@dataclass(frozen=True)
class TrainOptions:
    """Options of `train`.

    Attributes:
        arch: "gp" (Gaussian processes of the pose on the principal components of d; one
            camera), "mlp" (an ensemble of MLPs of the pose on the same components; one
            camera), "unet" (geometry images of X_N + pose, a U-Net; the only one that
            conditions on the camera) or "paper" (pose only; one camera). None: "gp" for
            one camera, "unet" for all cameras. On the built-in garment's test poses `gp` is
            the most accurate at every size measured, 120 to 960 training poses (README,
            benchmarks/tsnn_learning_curve.py).
        components: principal components of d that `gp` (each its own GP) and `mlp` model.
        widths: channels per U-Net level (None: (8, 16, 32, 64)).
        epochs: most passes over the training poses.
        resolution: atlas image size R; None: 64 on CPU, 512 on CUDA. d is smooth over the
            atlas, and on the built-in shirt 64² generalises as well as 128² (test MSE of d
            1.11e-5 vs 1.13e-5) at about 0.6x the training time.
        batch_size: samples ((pose, camera) pairs) per optimiser step (None: 16 for `paper`,
            8 for `unet`, which learns per step and is cheap per sample).
        lr: Adam learning rate (the paper's 1e-3).
        device: "cpu", "cuda", "cuda:1", ... or "auto" (CUDA when available).
        seed: seeds weight initialisation and batch order.
        patience: stop after this many epochs without a better validation loss.
        weight_assigned: loss weight of vertices whose d came from the ray (unassigned,
            extrapolated vertices weigh 1); above 1 favours what the camera sees.
        width: channels of the first decoder stage of `paper` (None: 256 on CPU and CUDA);
            hidden units of each layer of an `mlp` member (None: 128).
        min_width: fewest channels of any decoder stage (None: 8 on CPU, 16 on CUDA).
        lr_min_factor: the learning rate decays along a cosine from lr to lr * this factor
            over `epochs` (1.0: constant).
        dilation: texels each chart is extended by in atlas images (see AtlasSampler).
        weight_decay: decoupled weight decay (AdamW) on all parameters (0: the paper's plain Adam).
        pose_noise: std of Gaussian noise added to training poses, in units of each pose
            component's training std (augmentation; 0: off).
        dropout: dropout probability on the pose embedding (the first stage's input; 0: off).
        deterministic: use deterministic algorithms (always on CPU; on CUDA the bilinear
            sampling backward has no deterministic kernel, so it is off there by default).
        members: networks of an `mlp` ensemble (its hidden layers have `width` units, its
            outputs are `components` principal components of d).
    """

    arch: str | None = None
    components: int = 32
    widths: tuple[int, ...] | None = None
    epochs: int = 60
    resolution: int | None = None
    batch_size: int | None = None
    lr: float = 1e-3
    device: str = "auto"
    seed: int = 0
    patience: int = 15
    weight_assigned: float = 1.0
    width: int | None = None
    min_width: int | None = None
    lr_min_factor: float = 0.05
    dilation: int = 2
    deterministic: bool | None = None
    weight_decay: float = 0.0
    pose_noise: float = 0.0
    dropout: float = 0.0
    members: int = 5

    def __post_init__(self) -> None:
        check_field_types(self)
        if self.widths is not None and (isinstance(self.widths, (str, bytes)) or not hasattr(self.widths, "__iter__")
                                        or not all(isinstance(w, int) and not isinstance(w, bool) and w >= 1
                                                   for w in self.widths)):
            raise OptionError(f"widths must be a tuple of positive integers or None, got {self.widths!r:.60}")

    def resolved(self) -> "TrainOptions":
        """A copy with device, resolution and widths filled in for the device that runs it."""
        import torch

        device = self.device
        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        gpu = device.startswith("cuda")
        if gpu and not torch.cuda.is_available():
            raise OptionError(f"device {device!r} requested but CUDA is not available")
        def given(value, default):
            return default if value is None else value

        return replace(self, device=device,
                       resolution=given(self.resolution, (512 if self.arch == "paper" else 256) if gpu else 64),
                       widths=tuple(self.widths) if self.widths else (8, 16, 32, 64),
                       batch_size=given(self.batch_size, 16 if self.arch == "paper" else 8),
                       width=given(self.width, 128 if self.arch == "mlp" else 256),
                       min_width=given(self.min_width, 16 if gpu else 8),
                       deterministic=(not gpu) if self.deterministic is None else self.deterministic)

    def validate(self) -> None:
        if not isinstance(self.device, str) or not _DEVICE.match(self.device):
            raise OptionError(f"device must be auto, cpu, mps, cuda or cuda:N, got {self.device!r}")
        if self.resolution is not None and (not 8 <= self.resolution <= MAX_RESOLUTION
                                            or self.resolution & (self.resolution - 1)):
            raise OptionError(f"resolution must be a power of two in 8..{MAX_RESOLUTION}, got {self.resolution}")
        if self.width is not None and not 1 <= self.width <= MAX_WIDTH:
            raise OptionError(f"width must be in 1..{MAX_WIDTH}, got {self.width}")
        if self.arch is not None and self.arch not in ARCHS:
            raise OptionError(f"arch must be one of {', '.join(ARCHS)}, got {self.arch!r}")
        check_seed(self.seed)
        if self.arch == "unet" and self.resolution is not None:  # one halving per level
            levels = len(self.widths) if self.widths else 4
            if self.resolution < 2 ** levels:
                raise OptionError(f"resolution must be at least {2 ** levels} for the unet ({levels} levels), "
                                  f"got {self.resolution}")
        if not 1 <= self.components <= 256:
            raise OptionError(f"components must be in 1..256, got {self.components}")
        for name in ("epochs", "batch_size", "patience"):
            if getattr(self, name) < 1:
                raise OptionError(f"{name} must be at least 1, got {getattr(self, name)}")
        if not self.lr > 0 or not 0 < self.lr_min_factor <= 1 or not self.weight_assigned > 0 or self.weight_decay < 0:
            raise OptionError("lr and weight_assigned must be positive, weight_decay >= 0, lr_min_factor in (0, 1]")
        if not 1 <= self.members <= 32:
            raise OptionError(f"members must be in 1..32, got {self.members}")
        if self.pose_noise < 0 or not 0 <= self.dropout < 1:
            raise OptionError("pose_noise must be >= 0 and dropout in [0, 1)")


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


class _Data:
    """Targets of (pose, camera) samples of one split, as tensors on the training device.

    Attributes:
        x: (S,P) pose vectors. d: (S,n',2) targets. w: (S,n') loss weights.
        pose_row: (S,) index of the sample's pose in `poses` (and in `geometry`).
        camera: (S,) index of the sample's camera in the trainer's camera list.
        geometry: (K,G,R,R) geometry images of `poses` (unet only) or None.
    """

    def __init__(self, dataset, texcoords, cameras: list[str], poses: list[int], weight_assigned: float, device,
                 geometry=None):
        import torch

        n = len(texcoords.uv)
        pairs = [(row, c) for row in range(len(poses)) for c in range(len(cameras))]
        d = np.zeros((len(pairs), n, 2), np.float32)
        a = np.zeros((len(pairs), n), bool)
        for i, (row, c) in enumerate(pairs):
            d[i] = texcoords.displacement(cameras[c], poses[row])
            a[i] = texcoords.assigned(cameras[c], poses[row])
        bad = [cameras[c] for i, (_, c) in enumerate(pairs) if not np.all(np.isfinite(d[i]))]
        if bad:
            raise InputError(texcoords.path / bad[0] / "displacement.npy", "NaN or infinite displacements")
        self.poses = poses
        self.d_numpy = d
        rows = np.array([row for row, _ in pairs], dtype=np.int64)
        pose_vectors = np.asarray(dataset.poses[poses], dtype=np.float32).reshape(len(poses), dataset.poses.shape[1])
        self.x = torch.from_numpy(pose_vectors[rows] if len(pairs) else np.zeros((0, dataset.poses.shape[1]),
                                                                                     np.float32)).to(device)
        self.pose_row = torch.from_numpy(rows).to(device)
        self.camera = torch.from_numpy(np.array([c for _, c in pairs], dtype=np.int64)).to(device)
        self.d = torch.from_numpy(d).to(device)
        self.w = torch.from_numpy(np.where(a, weight_assigned, 1.0).astype(np.float32)).to(device)
        self.geometry = None if geometry is None else torch.from_numpy(geometry).to(device)

    def __len__(self) -> int:
        return len(self.d)


class _Forward:
    """Runs a network on samples of a `_Data`, whatever its architecture."""

    def __init__(self, model, cam_from_world=None):
        self.model = model
        self.cam_from_world = cam_from_world  # (C,3,4) tensor of the trainer's cameras, or None

    def __call__(self, data: _Data, idx, poses=None):
        x = data.x[idx] if poses is None else poses
        if not hasattr(self.model, "geometry_mean"):  # the paper's decoder: the pose alone
            return self.model(x)
        cams = self.cam_from_world[data.camera[idx]] if self.model.config.view else None
        return self.model(x, data.geometry[data.pose_row[idx]], cams)


def _weighted_mse(pred, target, weight):
    return ((pred - target).square().sum(-1) * weight).sum() / weight.sum()


def _evaluate(predict, data: _Data, batch_size: int) -> dict[str, float]:
    """Weighted MSE, unweighted RMSE and the zero predictor's weighted MSE over a sample set.

    Args:
        predict: (data, idx) -> (len(idx),n',2) per-vertex d of those samples (model in eval mode).
    """
    import torch

    if len(data) == 0:
        return {}
    se_w = w_sum = se = zero_w = 0.0
    with torch.no_grad():
        for start in range(0, len(data), batch_size):
            idx = torch.arange(start, min(start + batch_size, len(data)), device=data.d.device)
            pred = predict(data, idx)
            e = (pred - data.d[idx]).square().sum(-1)
            se_w += float((e * data.w[idx]).sum())
            w_sum += float(data.w[idx].sum())
            se += float(e.sum())
            zero_w += float((data.d[idx].square().sum(-1) * data.w[idx]).sum())
    n = len(data) * data.d.shape[1]
    return {"loss": se_w / w_sum, "rmse": math.sqrt(se / n), "zero_loss": zero_w / w_sum}


def train_camera(dataset, texcoords, camera: str, out: str | os.PathLike, options: TrainOptions = TrainOptions(),
                 progress: bool = True) -> TrainResult:
    """Train the texture sliding network of one camera (`train` with a camera name)."""
    return train(dataset, texcoords, out, camera=camera, options=options, progress=progress)


def _resolve(options: TrainOptions, camera: str | None) -> TrainOptions:
    """The options `train` runs with: the default architecture for a camera (`gp`) or for
    every camera (`unet`), then `TrainOptions.resolved`; ValueError if invalid."""
    if options.arch is None:
        options = replace(options, arch="gp" if camera is not None else "unet")
    options = options.resolved()
    options.validate()
    return options


def dataset_fingerprint(dataset) -> str:
    """What a model depends on of the dataset: its inferred shapes, poses, mesh and body."""
    from mvtex.util.fingerprint import fingerprint

    return fingerprint(dataset.inferred, dataset.poses, dataset.faces, dataset.uv, *dataset.body_arrays())


def _inputs_key(dataset, texcoords, cameras: Sequence[str], views: dict, split: dict, options: TrainOptions,
                dataset_hash: str | None = None) -> str:
    """Content fingerprint of everything a model is trained from: the dataset's inferred
    shapes, poses and mesh (and its body, when it has one), the texcoord set's mesh, poses
    and the cameras' arrays, the split, the cameras' views and the resolved options.
    config.json records it as "inputs"; `train_cameras` keeps a camera's model that records
    the key it would train with (the same inputs train the same model: bit for bit for `gp`)."""
    from mvtex.util.fingerprint import fingerprint, fingerprint_record

    record = {
        "version": MODEL_VERSION,
        "dataset": dataset_hash or dataset_fingerprint(dataset),
        "texcoords": {"mesh": fingerprint(texcoords.faces, texcoords.uv, texcoords.parent), "poses": texcoords.poses,
                      "cameras": {c: texcoords.fingerprint(c) for c in cameras}},
        "views": views, "split": split, "options": asdict(options),
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
            network's view inputs); needed when `camera` is None.
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
        best_epoch, seconds, losses {"train"|"val"|"test": {"loss", "rmse", "zero_loss"}},
        split sizes (poses).

    Raises:
        InputError: a camera or pose missing from the texcoord set or the rig, a texcoord
            mesh that is not the dataset mesh subdivided, overlapping uv charts.
        OptionError: bad options (`paper` without a camera name).
    """
    from mvtex.data.dataset import as_dataset
    from mvtex.data.rig import as_rig
    from mvtex.data.texcoords import as_texcoords
    from mvtex.util.checks import as_path, check_instance

    dataset = as_dataset(dataset)
    texcoords = as_texcoords(texcoords)
    out = as_path(out, "out")
    rig = None if rig is None else as_rig(rig)[0]
    check_instance(options, TrainOptions, "options")
    if camera is not None and not isinstance(camera, str):
        raise OptionError(f"camera must be a camera name or None, got {type(camera).__name__}")
    import torch

    out = Path(out)
    options = _resolve(options, camera)
    if camera is not None:
        if camera not in texcoords.cameras:
            raise InputError(texcoords.path, f"no camera {camera!r} in this texcoord set "
                             f"(it has {', '.join(texcoords.cameras)})")
        cameras = [camera]
    else:
        if options.arch in ("paper", "gp", "mlp"):
            raise OptionError(f"arch {options.arch} maps the pose alone: train it per camera (give a camera name)")
        if rig is None:
            raise OptionError("rig: a network for every camera needs the rig the texcoord set was made with")
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
    texcoords.check_dataset(dataset)
    faces, uv, parent = _check_texcoord_mesh(dataset, texcoords)
    split = _split(dataset, texcoords)
    if train_poses is not None:
        keep = {int(p) for p in train_poses}
        split["train"] = [p for p in split["train"] if p in keep]
        if not split["train"]:
            raise OptionError("train_poses: none of them is a training pose of the texcoord set")
    device = torch.device(options.device)
    t0 = time.perf_counter()

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
                                progress)
    finally:
        torch.use_deterministic_algorithms(previous_deterministic)
    model, config, history, best_epoch, losses = result
    seconds = time.perf_counter() - t0

    meta = {
        "format": MODEL_FORMAT, "version": MODEL_VERSION, "camera": camera,
        "inputs": _inputs_key(dataset, texcoords, cameras, views, split, options),
        "cameras": views or {camera: None},
        "architecture": config.to_dict(),
        "pose_normalisation": {"mean": model.pose_mean.cpu().tolist(), "std": model.pose_std.cpu().tolist()},
        "output_scale": float(model.output_scale),
        "mesh": {"subdiv": texcoords.subdiv, "num_base_vertices": int(dataset.num_vertices),
                 "num_vertices": int(len(uv)), "num_faces": int(len(faces)),
                 "base_mesh": mesh_fingerprint(dataset.faces, dataset.uv)},
        "atlas": {"convention": "texel (r, c) centre at (u, v) = ((c+0.5)/R, (r+0.5)/R); row 0 at v=0",
                  "dilation": options.dilation},
        "dataset": {"path": str(dataset.path), "name": dataset.name},
        "texcoords": {"path": str(texcoords.path), "source": texcoords.source, "subdiv": texcoords.subdiv},
        "split": split,
        "options": asdict(options),
        "device": str(device),
        "torch_version": torch.__version__,
        "epochs_run": len(history["train"]), "best_epoch": best_epoch,
        "seconds": round(seconds, 2),
        "losses": losses,
        "history": history,
    }
    _write_model(out, model, meta)
    return TrainResult(camera=camera, cameras=list(cameras), arch=options.arch, out=str(out), device=str(device),
                       resolution=getattr(config, "resolution", None), epochs_run=meta["epochs_run"],
                       best_epoch=best_epoch, seconds=meta["seconds"], num_poses={k: len(v) for k, v in split.items()},
                       losses=losses)


def _masked_stats(images: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel mean and std of (K,C,R,R) images over the texels of a (R,R) mask."""
    values = images[:, :, mask].transpose(1, 0, 2).reshape(images.shape[1], -1).astype(np.float64)
    return values.mean(1), values.std(1)


def _build(options: TrainOptions, sampler, train: _Data, views: dict, pose_dim: int, geometry_train):
    """The network with its normalisation set from the training samples."""
    import torch

    from mvtex.tsnn.model import TSNN, ModelConfig, UNet, UNetConfig

    mean_d = train.d_numpy.mean(axis=0)  # (n',2): the pose-independent part of d
    scale = float(np.sqrt(np.mean((train.d_numpy - mean_d) ** 2))) if len(train) > 1 else 0.0
    scale = max(scale, 1e-4)  # uv units; keeps a constant target from dividing by zero
    x_train = train.x.cpu().numpy()
    if options.arch == "paper":
        config = ModelConfig(pose_dim=pose_dim, resolution=options.resolution, width=options.width,
                             min_width=options.min_width, dropout=options.dropout)
        model = TSNN(config)
        model.set_normalisation(x_train.mean(0), x_train.std(0), scale)
    else:
        from mvtex.tsnn.geometry import NUM_CHANNELS

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


def _train(dataset, texcoords, cameras, views, faces, uv, parent, split, options: TrainOptions, device, progress):
    import torch
    from tqdm import tqdm

    from mvtex.tsnn.atlas import AtlasSampler

    sampler = AtlasSampler(faces, uv, options.resolution, dilation=options.dilation, source=texcoords.path / "mesh.npz")
    grid = sampler.grid().to(device)
    geometry = {k: None for k in split}
    if options.arch == "unet":
        from mvtex.tsnn.geometry import geometry_images

        geometry = {k: geometry_images(dataset, split[k], sampler, parent) for k in split}
    data = {k: _Data(dataset, texcoords, cameras, split[k], options.weight_assigned, device, geometry[k])
            for k in split}
    train = data["train"]
    monitor = "val" if len(data["val"]) else "train"
    model, config = _build(options, sampler, train, views, int(dataset.poses.shape[1]), geometry["train"])
    model.to(device)
    cams = torch.tensor([views[c] for c in cameras], dtype=torch.float32, device=device) if views else None
    forward = _Forward(model, cams)

    def vertices(data: _Data, idx):
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
            loss = _weighted_mse(pred, train.d[idx], train.w[idx])
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            total += float(loss.detach()) * len(idx)
        schedule.step()
        history["train"].append(total / max(1, sum(len(order[s:s + options.batch_size]) for s in starts)))
        if monitor == "val":
            model.eval()
            history["val"].append(_evaluate(vertices, data["val"], 64)["loss"])
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
    losses = {k: _evaluate(vertices, v, 64) for k, v in data.items() if len(v)}
    return model.cpu(), config, history, best[1], losses


class _Rows:
    """One camera's displacements of some poses, read `d[rows]` at a time from the texcoord
    set: (len(rows), n', 2) float32. Lets `gp` fit thousands of training poses without
    holding their d whole."""

    def __init__(self, texcoords, camera: str, poses: list[int]):
        self.texcoords, self.camera, self.poses = texcoords, camera, poses
        self.shape = (len(poses), len(texcoords.uv), 2)

    def __len__(self) -> int:
        return len(self.poses)

    def __getitem__(self, rows) -> np.ndarray:
        out = np.stack([self.texcoords.displacement(self.camera, self.poses[int(r)]) for r in np.atleast_1d(rows)])
        if not np.all(np.isfinite(out)):
            raise InputError(self.texcoords.path / self.camera / "displacement.npy", "NaN or infinite displacements")
        return out


def _train_gp(dataset, texcoords, camera: str, split, options: TrainOptions, device, progress):
    """`gp`: fit the Gaussian processes of one camera (float64, on `device`; the model comes
    back on the CPU); `_train`'s results. Every training pose is used (above `MAX_TRAIN`
    by the inducing-pose posterior); the training losses are those of at most `MAX_TRAIN`
    evenly spaced training poses."""
    from tqdm import tqdm

    from mvtex.tsnn.gp import MAX_TRAIN, fit_pose_gp
    from mvtex.tsnn.pca import evenly_spaced

    train_poses = split["train"]
    pose_vectors = np.asarray(dataset.poses[train_poses], dtype=np.float32).reshape(len(train_poses), -1)
    bar = tqdm(desc=f"train {camera} (gp, {len(train_poses)} poses)", unit="step", disable=not progress,
               file=sys.stderr)

    def advance(done: int, total: int) -> None:
        if bar.total != total:
            bar.total = total
            bar.refresh()
        bar.update(done - bar.n)

    model = fit_pose_gp(pose_vectors, _Rows(texcoords, camera, train_poses), components=options.components,
                        progress=advance, device=device)
    bar.close()
    scored = dict(split, train=[train_poses[i] for i in evenly_spaced(len(train_poses), MAX_TRAIN)])
    data = {k: _Data(dataset, texcoords, [camera], scored[k], options.weight_assigned, "cpu") for k in scored}

    def vertices(data: _Data, idx):
        return model(data.x[idx])

    losses = {k: _evaluate(vertices, v, 256) for k, v in data.items() if len(v)}
    return model, model.config, {"train": [], "val": []}, 0, losses


def _train_mlp(dataset, texcoords, camera: str, split, options: TrainOptions, progress):
    """`mlp`: fit an ensemble of MLPs on the principal components of one camera's d (on the
    CPU, float32), each member's epoch chosen on the validation poses; `_train`'s results.
    The training losses are those of at most `MAX_TRAIN` evenly spaced training poses."""
    from tqdm import tqdm

    from mvtex.tsnn.gp import MAX_TRAIN
    from mvtex.tsnn.mlp import fit_pose_mlp
    from mvtex.tsnn.pca import evenly_spaced

    train_poses = split["train"]
    pose_vectors = np.asarray(dataset.poses[train_poses], dtype=np.float32).reshape(len(train_poses), -1)
    val = _Data(dataset, texcoords, [camera], split["val"], options.weight_assigned, "cpu")
    bar = tqdm(desc=f"train {camera} (mlp, {len(train_poses)} poses)", unit="step", disable=not progress)

    def advance(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    model, history = fit_pose_mlp(pose_vectors, _Rows(texcoords, camera, train_poses), val.x.numpy(), val.d_numpy,
                                  components=options.components, hidden=options.width, members=options.members,
                                  seed=options.seed, lr=options.lr, progress=advance)
    bar.close()
    scored = dict(split, train=[train_poses[i] for i in evenly_spaced(len(train_poses), MAX_TRAIN)])
    data = {k: (val if k == "val" else _Data(dataset, texcoords, [camera], scored[k], options.weight_assigned, "cpu"))
            for k in scored}

    def vertices(data: _Data, idx):
        return model(data.x[idx])

    losses = {k: _evaluate(vertices, v, 256) for k, v in data.items() if len(v)}
    best = history.pop("best_epoch")
    return model, model.config, history, max(best), losses
