"""The model directory a TSNN or `gp` model lives in (model.safetensors, config.json, a
picture, and a `unet`'s geometry.npz): written here; config.json's keys are
`mvtex.tsnn.config.ModelConfig`'s.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, ClassVar, TypeVar

import numpy as np

from mvtex.data.mesh import apply_parent, subdivide
from mvtex.tsnn.config import (
    GEOMETRY_FILE,
    MODEL_FORMAT,
    MODEL_VERSION,
    READABLE_VERSIONS,
    ModelConfig,
    mesh_fingerprint,
)
from mvtex.util.errors import InputError
from mvtex.util.output import atomic_path

__all__ = ["MODEL_FORMAT", "MODEL_VERSION", "READABLE_VERSIONS", "TrainResult", "TrainedCameras", "mesh_fingerprint",
           "rebuild_mesh"]


def integer_config(cls, d: dict[str, Any], arch: str):
    """A config dataclass of integer fields from its dict (config.json's "architecture",
    "arch" left out), validated: ValueError on unknown keys or values that are not integers."""
    d = {k: v for k, v in d.items() if k != "arch"}
    unknown = set(d) - {f.name for f in fields(cls)}
    if unknown:
        raise ValueError(f"unknown architecture keys {sorted(unknown)}")
    if any(isinstance(v, bool) or not isinstance(v, int) for v in d.values()):
        raise ValueError(f"{arch} architecture values must be integers")
    config = cls(**d)
    config.validate()
    return config


_Config = TypeVar("_Config", bound="IntegerConfig")


class IntegerConfig:
    """A model's shape as a dataclass of integer fields, stored as config.json's
    "architecture" with its `ARCH` name (`to_dict`) and read back checked (`from_dict`)."""

    ARCH: ClassVar[str]

    def validate(self) -> None:
        """Raise ValueError on a shape the model cannot take."""

    def to_dict(self) -> dict[str, Any]:
        return {"arch": self.ARCH, **asdict(self)}  # type: ignore[call-overload]

    @classmethod
    def from_dict(cls: type[_Config], d: dict[str, Any]) -> _Config:
        return integer_config(cls, d, cls.ARCH)


@dataclass(frozen=True)
class TrainResult:
    """What `mvtex.tsnn.train.train` made (`mvtex train --json` is `to_json()`).

    Attributes:
        camera: the camera of a one-camera model, None for one network of every camera.
        cameras: the cameras the model predicts; arch: its architecture; out: its directory.
        device: where it was trained; resolution: its atlas resolution (None for `gp`).
        epochs_run, best_epoch, seconds: the training's course and time.
        num_poses: {"train", "val", "test"} pose counts; losses: the final losses per split.
        gain: the factor its predictions are multiplied by (`TrainOptions.gain`), None: off.
    """

    camera: str | None
    cameras: list[str]
    arch: str
    out: str
    device: str
    resolution: int | None
    epochs_run: int
    best_epoch: int
    seconds: float
    num_poses: dict[str, int]
    losses: dict[str, Any]
    gain: float | None = None

    def to_json(self) -> dict:
        return {"camera": self.camera, "cameras": list(self.cameras), "arch": self.arch, "out": self.out,
                "device": self.device, "resolution": self.resolution, "epochs_run": self.epochs_run,
                "best_epoch": self.best_epoch, "seconds": self.seconds, "num_poses": dict(self.num_poses),
                "losses": self.losses, "gain": self.gain}


@dataclass(frozen=True)
class TrainedCameras:
    """What `mvtex.tsnn.cameras.train_cameras` made: one model per camera, OUT/<camera>.

    Attributes:
        out: the parent directory; cameras: in the order asked; arch: the architecture (a
            sorted list if the kept models differ); models: camera -> its `TrainResult`;
        kept: the cameras whose models were kept from an earlier run with the same inputs.
    """

    out: str
    cameras: list[str]
    arch: str | list[str]
    models: dict[str, TrainResult]
    kept: list[str]

    def to_json(self) -> dict:
        return {"out": self.out, "cameras": list(self.cameras), "arch": self.arch,
                "models": {c: m.to_json() for c, m in self.models.items()}, "kept": list(self.kept)}


def rebuild_mesh(faces: np.ndarray, uv: np.ndarray, subdiv: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The texcoord-set mesh made from a dataset mesh: (faces (m',3) int32, uv (n',2) float32,
    parent (n',2) int32) after `subdiv` midpoint subdivisions."""
    sub = subdivide(faces, len(uv), int(subdiv))
    return sub.faces, apply_parent(np.asarray(uv, np.float32), sub.parent).astype(np.float32), sub.parent


# The loss plots' axes: what each architecture's history holds per epoch.
LOSS_AXIS = {"mlp": "squared error of d per vertex (uv²)",  # within the PCA basis: said in the title
             "paper": "weighted squared error of d per vertex (uv²)",
             "unet": "weighted squared error of d per vertex (uv²)"}


def _loss_plot(path: Path, history: dict[str, list[float]], best_epoch: int, title: str,
               axis: str = "weighted squared error of d per vertex (uv²)") -> None:
    # The object-oriented API with an Agg canvas: no global backend switch, no display.
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: PLC0415 (loaded on use)
    from matplotlib.figure import Figure  # noqa: PLC0415 (loaded on use)

    fig = Figure(figsize=(6, 4), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    epochs = np.arange(1, len(history["train"]) + 1)
    ax.semilogy(epochs, history["train"], label="train")
    if history.get("val"):
        ax.semilogy(epochs, history["val"], label="validation")
    ax.axvline(best_epoch, color="gray", linestyle=":", label=f"best (epoch {best_epoch})")
    ax.set_xlabel("epoch")
    ax.set_ylabel(axis)
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, format="png")


def _kept_model(path: Path, key: str) -> TrainResult | None:
    """The `train` result of the finished model directory at `path` if its config.json
    records inputs `key`; None if there is none, it is unreadable or it was trained from
    other inputs."""
    try:
        config = ModelConfig.read(path)
        if config.inputs != key or not (path / "model.safetensors").is_file():
            return None
        return TrainResult(camera=config.camera, cameras=list(config.cameras), arch=config.options["arch"],
                           out=str(path), device=config.device, resolution=config.architecture.get("resolution"),
                           epochs_run=config.epochs_run, best_epoch=config.best_epoch, seconds=config.seconds,
                           num_poses={k: len(v) for k, v in config.split.items()}, losses=config.losses,
                           gain=config.gain)
    except (InputError, OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


def _relevance_plot(path: Path, relevance: np.ndarray, title: str) -> None:
    """Heatmap of a `gp` model's inverse lengthscales: component (rows) x pose coordinate."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: PLC0415 (loaded on use)
    from matplotlib.figure import Figure  # noqa: PLC0415 (loaded on use)

    c, p = relevance.shape
    fig = Figure(figsize=(min(12.0, 2.0 + 0.45 * p), min(8.0, 1.6 + 0.3 * c)), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    image = ax.imshow(relevance, cmap="viridis", aspect="auto", interpolation="nearest")
    ax.set_xlabel("pose coordinate")
    ax.set_ylabel("principal component of d")
    ax.set_xticks(range(p))
    ax.set_title(title, fontsize=9)
    fig.colorbar(image, ax=ax, label="1 / lengthscale (standardised pose)")
    fig.tight_layout()
    fig.savefig(path, format="png")


def _write_model(out: Path, model, config: ModelConfig, geometry: dict[str, np.ndarray] | None = None) -> None:
    """Write a model directory atomically: the weights, config.json, its picture and, given
    `geometry` (a `unet`'s reference arrays, `MeshGeometry.reference_arrays`), geometry.npz."""
    from safetensors.torch import save  # noqa: PLC0415 (loaded on use)

    arch = config.architecture
    with atomic_path(out) as tmp:
        tmp.mkdir()
        state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
        # One metadata entry: safetensors writes its metadata map in hash order, which varies
        # from process to process, and a model's bytes should not (the cameras are in config.json).
        # Serialised in memory and written by Python: a failed write (a full disk, a file-size
        # limit) is then an OSError the writer policy names the output by, not safetensors' own
        # error type.
        (tmp / "model.safetensors").write_bytes(save(state, metadata={"format": MODEL_FORMAT}))
        if geometry is not None:
            with open(tmp / GEOMETRY_FILE, "wb") as f:
                np.savez(f, **geometry)
        config.write(tmp)
        if arch["arch"] == "gp":
            _relevance_plot(tmp / "relevance.png", model.relevance(),
                            f"gp {config.camera}: relevance of the pose coordinates "
                            f"({arch['num_train']} training poses)")
        else:
            name = arch["arch"]
            _loss_plot(tmp / "loss.png", config.history, config.best_epoch,
                       f"{name} model of {'camera ' + config.camera if config.camera else 'all cameras'} "
                       + (f"({arch['resolution']}², " if "resolution" in arch else "(")
                       + f"best epoch {config.best_epoch})"
                       + ("\nthe error of d within its principal components" if name == "mlp" else ""),
                       axis=LOSS_AXIS.get(name, LOSS_AXIS["paper"]))


def read_weights(weights: Path) -> dict:
    """The tensors of a model's model.safetensors, on the CPU (never unpickled); InputError
    naming the file when it is missing or unreadable."""
    from safetensors import SafetensorError  # noqa: PLC0415 (loaded on use)
    from safetensors.torch import load_file  # noqa: PLC0415 (loaded on use)

    if not weights.is_file():
        raise InputError(weights, "file not found")
    try:
        return load_file(str(weights), device="cpu")
    except (SafetensorError, OSError, ValueError, MemoryError) as err:
        raise InputError(weights, f"not a readable safetensors file ({err})") from None
