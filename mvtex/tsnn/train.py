"""Training one texture sliding network (one camera) on a texcoord set.

The targets are the texcoord set's per-vertex displacements d (on its possibly subdivided
mesh); the network's image is read at every vertex's T_G with bilinear sampling and the
loss is the (optionally weighted) mean squared error of d over vertices and poses
(DESIGN §5 TSNN). Adam at lr 1e-3, the dataset's train/val/test split restricted to the
poses of the texcoord set, early stopping on the validation loss.

A model directory holds:

    model.safetensors   the state dict (weights, batch-norm statistics, pose normalisation)
    config.json         {"format": "mvtex-tsnn", "version": 1, "camera", "architecture",
                         "pose_normalisation", "mesh" (subdiv, vertex counts, base-mesh hash),
                         "split", "options", "losses", "history", ...}
    loss.png            training and validation loss per epoch
"""

from __future__ import annotations

import hashlib
import math
import os
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..io import atomic_path
from ..mesh import apply_parent, subdivide

MODEL_FORMAT = "mvtex-tsnn"
MODEL_VERSION = 1


MAX_RESOLUTION = 2048  # atlas image size: 2·R² floats per pose and per batch item
MAX_WIDTH = 1024  # channels of the first stage
MAX_SUBDIV = 3

@dataclass(frozen=True)
class TrainOptions:
    """Options of `train_camera`.

    Attributes:
        epochs: most passes over the training poses.
        resolution: atlas image size R; None: 64 on CPU, 512 on CUDA. d is smooth over the
            atlas, and on the built-in shirt 64² generalises as well as 128² (test MSE of d
            1.11e-5 vs 1.13e-5) at about 0.6x the training time.
        batch_size: poses per optimiser step.
        lr: Adam learning rate (the paper's 1e-3).
        device: "cpu", "cuda", "cuda:1", ... or "auto" (CUDA when available).
        seed: seeds weight initialisation and batch order.
        patience: stop after this many epochs without a better validation loss.
        weight_assigned: loss weight of vertices whose d came from the ray (unassigned,
            extrapolated vertices weigh 1); above 1 favours what the camera sees.
        width: channels of the first decoder stage (None: 256 on CPU and CUDA).
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
    """

    epochs: int = 60
    resolution: int | None = None
    batch_size: int = 16
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

    def resolved(self) -> "TrainOptions":
        """A copy with device, resolution and widths filled in for the device that runs it."""
        import torch

        device = self.device
        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        gpu = device.startswith("cuda")
        if gpu and not torch.cuda.is_available():
            raise ValueError(f"device {device!r} requested but CUDA is not available")
        return replace(self, device=device,
                       resolution=self.resolution or (512 if gpu else 64),
                       width=self.width or 256,
                       min_width=self.min_width or (16 if gpu else 8),
                       deterministic=(not gpu) if self.deterministic is None else self.deterministic)

    def validate(self) -> None:
        if self.resolution is not None and (not 8 <= self.resolution <= MAX_RESOLUTION
                                            or self.resolution & (self.resolution - 1)):
            raise ValueError(f"resolution must be a power of two in 8..{MAX_RESOLUTION}, got {self.resolution}")
        if self.width is not None and not 1 <= self.width <= MAX_WIDTH:
            raise ValueError(f"width must be in 1..{MAX_WIDTH}, got {self.width}")
        for name in ("epochs", "batch_size", "patience"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if not self.lr > 0 or not 0 < self.lr_min_factor <= 1 or not self.weight_assigned > 0 or self.weight_decay < 0:
            raise ValueError("lr and weight_assigned must be positive, weight_decay >= 0, lr_min_factor in (0, 1]")
        if self.pose_noise < 0 or not 0 <= self.dropout < 1:
            raise ValueError("pose_noise must be >= 0 and dropout in [0, 1)")


def mesh_fingerprint(faces: np.ndarray, uv: np.ndarray) -> str:
    """SHA-256 of a base mesh's faces (int32) and uv (float32): ties a model to its mesh."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(faces, dtype=np.int32).tobytes())
    h.update(np.ascontiguousarray(uv, dtype=np.float32).tobytes())
    return h.hexdigest()


def rebuild_mesh(faces: np.ndarray, uv: np.ndarray, subdiv: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The texcoord-set mesh made from a dataset mesh: (faces (m',3) int32, uv (n',2) float32,
    parent (n',2) int32) after `subdiv` midpoint subdivisions."""
    sub = subdivide(faces, len(uv), int(subdiv))
    return sub.faces, apply_parent(np.asarray(uv, np.float32), sub.parent).astype(np.float32), sub.parent


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


def _loss_plot(path: Path, history: dict[str, list[float]], best_epoch: int, title: str) -> None:
    # The object-oriented API with an Agg canvas: no global backend switch, no display.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 4), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    epochs = np.arange(1, len(history["train"]) + 1)
    ax.semilogy(epochs, history["train"], label="train")
    if history.get("val"):
        ax.semilogy(epochs, history["val"], label="validation")
    ax.axvline(best_epoch, color="gray", linestyle=":", label=f"best (epoch {best_epoch})")
    ax.set_xlabel("epoch")
    ax.set_ylabel("weighted MSE of d (uv²)")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, format="png")


class _Data:
    """Targets of one camera for a list of poses, as tensors on the training device."""

    def __init__(self, dataset, texcoords, camera: str, poses: list[int], weight_assigned: float, device):
        import torch

        n = len(texcoords.uv)
        d = np.stack([texcoords.displacement(camera, p) for p in poses]).astype(np.float32) if poses \
            else np.zeros((0, n, 2), np.float32)
        a = np.stack([texcoords.assigned(camera, p) for p in poses]).astype(bool) if poses else np.zeros((0, n), bool)
        if not np.all(np.isfinite(d)):
            raise InputError(texcoords.path / camera / "displacement.npy", "NaN or infinite displacements")
        self.poses = poses
        self.d_numpy = d
        pose_dim = int(dataset.poses.shape[1])
        self.x = torch.from_numpy(np.asarray(dataset.poses[poses], dtype=np.float32).reshape(len(poses), pose_dim)).to(device)
        self.d = torch.from_numpy(d).to(device)
        self.w = torch.from_numpy(np.where(a, weight_assigned, 1.0).astype(np.float32)).to(device)

    def __len__(self) -> int:
        return len(self.poses)


def _weighted_mse(pred, target, weight):
    return ((pred - target).square().sum(-1) * weight).sum() / weight.sum()


def _evaluate(model, sampler, grid, data: _Data, batch_size: int) -> dict[str, float]:
    """Weighted MSE, unweighted RMSE and the zero predictor's weighted MSE over a pose set."""
    import torch

    if len(data) == 0:
        return {}
    model.eval()
    se_w = w_sum = se = zero_w = 0.0
    with torch.no_grad():
        for start in range(0, len(data), batch_size):
            sl = slice(start, start + batch_size)
            pred = sampler.sample(model(data.x[sl]), grid)
            e = (pred - data.d[sl]).square().sum(-1)
            se_w += float((e * data.w[sl]).sum())
            w_sum += float(data.w[sl].sum())
            se += float(e.sum())
            zero_w += float((data.d[sl].square().sum(-1) * data.w[sl]).sum())
    n = len(data) * data.d.shape[1]
    return {"loss": se_w / w_sum, "rmse": math.sqrt(se / n), "zero_loss": zero_w / w_sum}


def train_camera(dataset, texcoords, camera: str, out: str | os.PathLike, options: TrainOptions = TrainOptions(),
                 progress: bool = True) -> dict[str, Any]:
    """Train the texture sliding network of one camera and write a model directory.

    Args:
        dataset: the `mvtex.dataset.Dataset` the texcoord set was made from (poses, split, mesh).
        texcoords: an opened `TexcoordSet` holding `camera`.
        camera: camera name.
        out: model directory to write (replaced atomically).
        options: see `TrainOptions`.
        progress: show a progress bar with the losses on stderr.

    Returns:
        A JSON-serialisable summary: camera, out, device, epochs_run, best_epoch, seconds,
        losses {"train"|"val"|"test": {"loss", "rmse", "zero_loss"}}, split sizes.

    Raises:
        InputError: a camera or pose missing from the texcoord set, a texcoord mesh that is
            not the dataset mesh subdivided, overlapping uv charts.
    """
    import torch

    out = Path(out)
    try:
        options = options.resolved()
        options.validate()
    except ValueError as err:
        raise InputError(None, f"training options: {err}") from None
    if camera not in texcoords.cameras:
        raise InputError(texcoords.path, f"no camera {camera!r} in this texcoord set (it has {', '.join(texcoords.cameras)})")
    faces, uv, _ = _check_texcoord_mesh(dataset, texcoords)
    split = _split(dataset, texcoords)
    device = torch.device(options.device)
    t0 = time.perf_counter()

    previous_deterministic = torch.are_deterministic_algorithms_enabled()
    try:
        torch.use_deterministic_algorithms(bool(options.deterministic))
        with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
            torch.manual_seed(options.seed)
            result = _train(dataset, texcoords, camera, faces, uv, split, options, device, progress)
    finally:
        torch.use_deterministic_algorithms(previous_deterministic)
    model, config, history, best_epoch, losses = result
    seconds = time.perf_counter() - t0

    meta = {
        "format": MODEL_FORMAT, "version": MODEL_VERSION, "camera": camera,
        "architecture": config.to_dict(),
        "pose_normalisation": {"mean": model.pose_mean.cpu().tolist(), "std": model.pose_std.cpu().tolist()},
        "output_scale": float(model.output_scale),
        "mesh": {"subdiv": texcoords.subdiv, "num_base_vertices": int(dataset.num_vertices),
                 "num_vertices": int(len(uv)), "num_faces": int(len(faces)),
                 "base_mesh_sha256": mesh_fingerprint(dataset.faces, dataset.uv)},
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
    return {"camera": camera, "out": str(out), "device": str(device), "resolution": config.resolution,
            "epochs_run": meta["epochs_run"], "best_epoch": best_epoch, "seconds": meta["seconds"],
            "num_poses": {k: len(v) for k, v in split.items()}, "losses": losses}


def _train(dataset, texcoords, camera, faces, uv, split, options: TrainOptions, device, progress):
    import torch
    from tqdm import tqdm

    from .atlas import AtlasSampler
    from .model import TSNN, ModelConfig

    sampler = AtlasSampler(faces, uv, options.resolution, dilation=options.dilation, source=texcoords.path / "mesh.npz")
    grid = sampler.grid().to(device)
    data = {k: _Data(dataset, texcoords, camera, split[k], options.weight_assigned, device) for k in split}
    train = data["train"]
    monitor = "val" if len(data["val"]) else "train"

    config = ModelConfig(pose_dim=int(train.x.shape[1]), resolution=options.resolution, width=options.width,
                         min_width=options.min_width, dropout=options.dropout)
    model = TSNN(config)
    mean_d = train.d_numpy.mean(axis=0)  # (n',2): the pose-independent part of d
    scale = float(np.sqrt(np.mean((train.d_numpy - mean_d) ** 2))) if len(train) > 1 else 0.0
    scale = max(scale, 1e-4)  # uv units; keeps a constant target from dividing by zero
    x_train = train.x.cpu().numpy()
    model.set_normalisation(x_train.mean(0), x_train.std(0), scale)
    with torch.no_grad():
        bias = sampler.to_image(mean_d / scale)  # (R,R,2), row 0 at v = 0
        model.bias.copy_(torch.from_numpy(bias).permute(2, 0, 1)[None])
    model.to(device)

    optimiser = torch.optim.AdamW(model.parameters(), lr=options.lr, weight_decay=options.weight_decay)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, T_max=options.epochs,
                                                          eta_min=options.lr * options.lr_min_factor)
    generator = torch.Generator().manual_seed(options.seed)
    history: dict[str, list[float]] = {"train": [], "val": []}
    best = (math.inf, 0, None)
    bar = tqdm(range(1, options.epochs + 1), desc=f"train {camera}", unit="epoch", disable=not progress, leave=True)
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
            pred = sampler.sample(model(x), grid)
            loss = _weighted_mse(pred, train.d[idx], train.w[idx])
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            total += float(loss.detach()) * len(idx)
        schedule.step()
        history["train"].append(total / max(1, sum(len(order[s:s + options.batch_size]) for s in starts)))
        if monitor == "val":
            history["val"].append(_evaluate(model, sampler, grid, data["val"], 64)["loss"])
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
    losses = {k: _evaluate(model, sampler, grid, v, 64) for k, v in data.items() if len(v)}
    return model.cpu(), config, history, best[1], losses


def _write_model(out: Path, model, meta: dict[str, Any]) -> None:
    import json

    from safetensors.torch import save_file

    with atomic_path(out) as tmp:
        tmp.mkdir()
        state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
        save_file(state, str(tmp / "model.safetensors"), metadata={"format": MODEL_FORMAT, "camera": meta["camera"]})
        (tmp / "config.json").write_text(json.dumps(meta, indent=2) + "\n")
        _loss_plot(tmp / "loss.png", meta["history"], meta["best_epoch"],
                   f"TSNN {meta['camera']} ({meta['architecture']['resolution']}², best epoch {meta['best_epoch']})")
