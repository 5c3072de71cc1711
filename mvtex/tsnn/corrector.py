"""The geometry corrector (`mvtex train --geometry`): the pose -> gt - inferred, per vertex.

The plain alternative to texture sliding: the smooth inferred mesh and the ground truth
share their vertices, so the wrinkles the predictor missed are a per-vertex 3-D residual
r = gt - inferred, (n,3) per pose. The corrector models it as `gp` models a camera's d
(`mvtex.tsnn.gp`, `mvtex.tsnn.pca`): the first C principal components of the training
residuals, each coefficient an exact Gaussian process of the standardised pose (a
subset-of-regressors one on 2,000 inducing poses above 2,000 training poses), with
hyperparameters by maximum marginal likelihood:

    r(θ) = mean + Σ_c f_c(θ) · basis_c,      σ_i(θ)² = s² (Σ_c var_c(θ) basis_ci² + trunc_i)

σ_i is the predictive standard deviation of vertex i in meters (the root of the expected
squared length of its error, summed over x, y, z), from each component's posterior
variance carried through the basis plus what the C components leave out, times one
factor s chosen on the validation poses: with it, the mean squared error of the corrected
vertices equals their mean predicted variance there (`calibrate_sigma`).

Out of sample. A pose the model was conditioned on would be corrected by its own
residual, all but exactly, and models stacked on a corrected set would learn from errors
they never meet at run time. So for every training pose the model keeps its
out-of-sample prediction: the closed-form leave-one-out of each component's GP (Rasmussen
& Williams eq. 5.12: mean y_i - [A⁻¹y]_i / [A⁻¹]_ii, variance 1 / [A⁻¹]_ii with A the
noisy kernel matrix, the same hyperparameters), or above the exact limit `FOLDS`-fold
predictions of the sparse GP (`mvtex.tsnn.gp.fit_components`, from the factorisations
the fit makes anyway). The principal components and the hyperparameters are those of all
training poses. `GeometryCorrector.predict` gives a pose
whose pose vector is a training pose's (bit for bit) that prediction, any other pose the
posterior's; so an inference set of the same frames is corrected exactly as its dataset.

A model directory: model.safetensors (`GeometryCorrector`'s buffers), config.json
{"format": "mvtex-geometry", "version", "architecture", "mesh" (vertex count and base-mesh
fingerprint), "pose_dim", "dataset", "split", "options", "calibration", "validation",
"out_of_sample", "seconds"}.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from torch import nn

from mvtex.data.dataset import as_dataset, content_fingerprint
from mvtex.data.mesh import rms_distance
from mvtex.tsnn.config import mesh_fingerprint
from mvtex.tsnn.gp import GPConfig, PoseGP, fit_components
from mvtex.tsnn.modeldir import IntegerConfig, read_weights
from mvtex.tsnn.options import GeometryOptions
from mvtex.tsnn.pca import pose_pca_counted, residual_var
from mvtex.tsnn.train import resolve_device
from mvtex.util.checks import as_path, check_instance
from mvtex.util.errors import InputError
from mvtex.util.files import read_json, read_row
from mvtex.util.output import atomic_path, readable, writer
from mvtex.util.progress import step_bar

GEOMETRY_FORMAT = "mvtex-geometry"


GEOMETRY_VERSION = 1


FOLDS = 10  # out-of-sample predictions of a sparse (inducing-pose) model: this many folds


MAX_POSES = 1_000_000  # training poses a model directory may record


_BLOCK = 256  # poses predicted at a time


@dataclass(frozen=True)
class CorrectorConfig(IntegerConfig):
    """Shape of a `GeometryCorrector`.

    Attributes:
        pose_dim: P. num_vertices: n. components: C.
        num_train: poses the GP's posterior is expanded on (at most `MAX_TRAIN`).
        training_poses: K, the training poses whose out-of-sample prediction it keeps.
    """

    ARCH = "geometry-gp"

    pose_dim: int
    num_vertices: int
    num_train: int
    components: int
    training_poses: int

    def validate(self) -> None:
        self.gp_config().validate()
        if not self.num_train <= self.training_poses <= MAX_POSES:
            raise ValueError(f"training_poses must be in num_train..{MAX_POSES}, got {self.training_poses}")

    def gp_config(self) -> GPConfig:
        return GPConfig(pose_dim=self.pose_dim, num_vertices=self.num_vertices, num_train=self.num_train,
                        components=self.components, channels=3)



class GeometryCorrector(nn.Module):
    """The residual gt - inferred of poses, with its per-vertex σ (`predict`).

    Submodule `gp` (a 3-channel `PoseGP`); buffers: train_poses (K,P) float32 the
    training pose vectors, oos_mean and oos_var (K,C) float64 each training pose's
    out-of-sample coefficients and their variances, sigma_scale () the calibration
    factor of σ.
    """

    train_poses: torch.Tensor  # a buffer
    oos_mean: torch.Tensor  # a buffer
    oos_var: torch.Tensor  # a buffer
    sigma_scale: torch.Tensor  # a buffer

    def __init__(self, config: CorrectorConfig):
        super().__init__()
        config.validate()
        self.config = config
        k, p, c = config.training_poses, config.pose_dim, config.components
        self.gp = PoseGP(config.gp_config())
        self.register_buffer("train_poses", torch.zeros(k, p, dtype=torch.float32))
        self.register_buffer("oos_mean", torch.zeros(k, c, dtype=torch.float64))
        self.register_buffer("oos_var", torch.zeros(k, c, dtype=torch.float64))
        self.register_buffer("sigma_scale", torch.tensor(1.0, dtype=torch.float64))
        self._index: dict[bytes, int] | None = None

    def training_rows(self, poses: np.ndarray) -> np.ndarray:
        """(B,) the training row of each pose vector (B,P) equal to a training pose's as
        float32, bit for bit; -1 for the others."""
        if self._index is None:
            rows = self.train_poses.cpu().numpy()
            self._index = {row.tobytes(): i for i, row in enumerate(rows)}
        x = np.ascontiguousarray(poses, dtype=np.float32)
        return np.array([self._index.get(row.tobytes(), -1) for row in x], dtype=np.int64)

    def predict(self, poses: np.ndarray, out_of_sample: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The residual and its σ at pose vectors (B,P).

        Args:
            out_of_sample: a training pose gets its out-of-sample prediction (else every
                pose the posterior's).

        Returns:
            residual (B,n,3) float64 (meters), sigma (B,n) float64 (meters, calibrated),
            in_sample (B,) bool: the poses that are training poses.
        """
        x = torch.from_numpy(np.asarray(poses, dtype=np.float64).reshape(len(poses), -1))
        with torch.no_grad():
            coef = self.gp.coefficients(x)
            var = self.gp.coefficient_variance(x)
            rows = self.training_rows(np.asarray(poses)) if out_of_sample else np.full(len(x), -1)
            seen = torch.from_numpy(rows >= 0)
            if bool(seen.any()):
                index = torch.from_numpy(rows[rows >= 0])
                coef[seen] = self.oos_mean[index]
                var[seen] = self.oos_var[index]
            residual = self.gp.values(coef).numpy()
            sigma = (self.sigma_scale * self.gp.vertex_std(var)).numpy()
        return residual, sigma, rows >= 0


class _Residuals:
    """gt - inferred of some poses, read `r[rows]` at a time: (len(rows), n, 3) float64."""

    def __init__(self, dataset, poses: list[int]):
        self.dataset, self.poses = dataset, poses
        self.shape = (len(poses), dataset.num_vertices, 3)

    def __len__(self) -> int:
        return len(self.poses)

    def __getitem__(self, rows) -> np.ndarray:
        ds = self.dataset
        return np.stack([read_row(ds.gt, self.poses[int(r)]).astype(np.float64)
                         - read_row(ds.inferred, self.poses[int(r)]).astype(np.float64) for r in np.atleast_1d(rows)])


def calibrate_sigma(errors2: np.ndarray, variances: np.ndarray) -> float:
    """The factor s of σ that makes the mean squared error equal the mean predicted variance
    s² σ² over the given vertices (1 when either is 0 or not finite)."""
    e, v = float(np.mean(errors2)), float(np.mean(variances))
    s = math.sqrt(e / v) if v > 0 and e > 0 and math.isfinite(e / v) else 1.0
    return s


@dataclass(frozen=True)
class GeometryResult:
    """What `train_geometry` made (`mvtex train --geometry --json` is `to_json()`).

    Attributes:
        out: the model directory. components: C modelled. num_poses: {"train","val","test"}.
        out_of_sample: "leave-one-out" (exact) or "10-fold" (sparse).
        sigma_scale: the calibration factor of σ. seconds: the fit's time.
        validation: on the validation poses, all vertices: "rmse_m" {"inferred",
            "corrected"} (mean over poses), "ratio" {"median", "worst"} of inferred /
            corrected RMSE per pose, "mean_sigma_m" and "rmse_error_m" (calibrated).
    """

    out: str
    components: int
    num_poses: dict[str, int]
    out_of_sample: str
    sigma_scale: float
    seconds: float
    validation: dict[str, Any]

    def to_json(self) -> dict:
        return asdict(self)


def _validation(model: GeometryCorrector, dataset, poses: list[int]) -> tuple[float, dict[str, Any]]:
    """Calibrate σ on the validation poses and measure the correction there."""
    inferred_rmse, corrected_rmse, err2, var = [], [], [], []
    for start in range(0, len(poses), _BLOCK):
        rows = poses[start:start + _BLOCK]
        x = np.asarray(dataset.poses[rows], np.float64).reshape(len(rows), -1)
        residual, sigma, _ = model.predict(x, out_of_sample=False)  # σ with scale 1 (not yet calibrated)
        for i, k in enumerate(rows):
            gt = read_row(dataset.gt, k).astype(np.float64)
            inferred = read_row(dataset.inferred, k).astype(np.float64)
            corrected = inferred + residual[i]
            inferred_rmse.append(rms_distance(inferred, gt))
            corrected_rmse.append(rms_distance(corrected, gt))
            err2.append(np.sum((corrected - gt) ** 2, axis=1))
            var.append(sigma[i] ** 2)
    e2, v = np.concatenate(err2), np.concatenate(var)
    scale = calibrate_sigma(e2, v)
    ratio = np.array(inferred_rmse) / np.maximum(np.array(corrected_rmse), 1e-300)
    return scale, {"poses": len(poses), "rmse_m": {"inferred": float(np.mean(inferred_rmse)),
                                                   "corrected": float(np.mean(corrected_rmse))},
                   "ratio": {"median": float(np.median(ratio)), "worst": float(ratio.min())},
                   "rmse_error_m": float(np.sqrt(np.mean(e2))), "mean_sigma_m": float(scale * np.sqrt(np.mean(v)))}


def fit_corrector(dataset, train_poses: list[int], options: GeometryOptions = GeometryOptions(),
                  progress: Callable[[int, int], None] | None = None) -> tuple[GeometryCorrector, str]:
    """The corrector of a dataset's training poses, σ not yet calibrated (scale 1).

    Returns:
        the model (eval mode, CPU) and how its training poses' predictions were made out
        of sample ("leave-one-out" or "10-fold").
    """
    options = replace(options, device=resolve_device(options.device))
    x = np.asarray(dataset.poses[train_poses], np.float64).reshape(len(train_poses), -1)
    residuals = _Residuals(dataset, train_poses)
    pca, reads = pose_pca_counted(x, residuals, options.components, progress)
    _, _, _, mean_d, basis, coef = pca
    gp, (mean, var) = fit_components(pca, residual_var(residuals, mean_d, basis, coef), 3, options.iterations,
                                     progress, options.device, reads=reads, out_of_sample=FOLDS)
    config = CorrectorConfig(pose_dim=gp.config.pose_dim, num_vertices=gp.config.num_vertices,
                             num_train=gp.config.num_train, components=gp.config.components,
                             training_poses=len(train_poses))
    model = GeometryCorrector(config)
    model.gp.load_state_dict(gp.state_dict())
    exact = len(train_poses) == gp.config.num_train
    with torch.no_grad():
        model.train_poses.copy_(torch.from_numpy(x.astype(np.float32)))
        model.oos_mean.copy_(torch.from_numpy(mean))
        model.oos_var.copy_(torch.from_numpy(np.maximum(var, 0.0)))
    model.eval()
    return model, "leave-one-out" if exact else f"{FOLDS}-fold"


@writer("train", inputs=lambda a: (a["dataset"],))
def train_geometry(dataset, out: str | os.PathLike, *, options: GeometryOptions = GeometryOptions(),
                   progress: bool = True, overwrite: bool = False) -> GeometryResult:
    """Fit the geometry corrector of a dataset (`mvtex train DATA --geometry --out GEOM`).

    Trained on the dataset's training poses; σ calibrated, and the correction measured, on
    its validation poses (needed); the test poses are not read.

    Args:
        dataset: a `mvtex.data.dataset.Dataset` or its directory (with gt).
        out: the model directory to write (replaced atomically).
        options: see `GeometryOptions`.
        progress: a progress bar on stderr.
        overwrite: replace another command's output at `out` (the writer policy).

    Raises:
        InputError: a dataset without training or validation poses.
    """

    out = as_path(out, "out")
    check_instance(options, GeometryOptions, "options")
    dataset = as_dataset(dataset)
    split = {k: [int(p) for p in dataset.split[k]] for k in ("train", "val", "test")}
    if len(split["train"]) < 2:
        raise InputError(dataset.path, f"the geometry corrector needs at least 2 training poses, the split has "
                         f"{len(split['train'])}")
    if not split["val"]:
        raise InputError(dataset.path, "the geometry corrector calibrates its uncertainty on the validation poses, "
                         "and the split has none: give the dataset a split.json with a non-empty 'val'")
    options = replace(options, device=resolve_device(options.device))
    t0 = time.perf_counter()
    bar, advance = step_bar(f"train geometry ({len(split['train'])} poses)", progress)

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        model, method = fit_corrector(dataset, split["train"], options, advance)
    bar.close()
    scale, validation = _validation(model, dataset, split["val"])
    with torch.no_grad():
        model.sigma_scale.fill_(scale)
    seconds = round(time.perf_counter() - t0, 2)
    meta = {
        "format": GEOMETRY_FORMAT, "version": GEOMETRY_VERSION,
        "architecture": model.config.to_dict(),
        "mesh": {"num_vertices": int(dataset.num_vertices), "base_mesh": mesh_fingerprint(dataset.faces, dataset.uv)},
        "pose_dim": int(dataset.poses.shape[1]),
        "dataset": {"path": str(dataset.path), "name": dataset.name, "content": content_fingerprint(dataset)},
        "split": split, "options": asdict(options),
        "out_of_sample": {"method": method, "poses": len(split["train"])},
        "calibration": {"sigma_scale": scale, "poses": "val"},
        "validation": validation, "torch_version": torch.__version__, "seconds": seconds,
    }
    _write(Path(out), model, meta)
    return GeometryResult(out=str(out), components=model.config.components,
                          num_poses={k: len(v) for k, v in split.items()}, out_of_sample=method, sigma_scale=scale,
                          seconds=seconds, validation=validation)


def _write(out: Path, model: GeometryCorrector, meta: dict[str, Any]) -> None:
    from safetensors.torch import save_file  # noqa: PLC0415 (loaded on use)

    with atomic_path(out) as tmp:
        tmp.mkdir()
        state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
        save_file(state, str(tmp / "model.safetensors"), metadata={"format": GEOMETRY_FORMAT})
        readable(tmp / "model.safetensors")
        (tmp / "config.json").write_text(json.dumps(meta, indent=2) + "\n")


@dataclass
class LoadedCorrector:
    """A geometry model directory opened: its path, config.json and the `GeometryCorrector`."""

    path: Path
    meta: dict[str, Any]
    model: GeometryCorrector

    def check_dataset(self, dataset) -> None:
        """InputError (naming the model's config.json) unless the dataset has the mesh and
        the pose size the model was made for."""
        file = self.path / "config.json"
        mesh = self.meta["mesh"]
        if mesh["num_vertices"] != dataset.num_vertices or mesh["base_mesh"] != mesh_fingerprint(dataset.faces,
                                                                                                 dataset.uv):
            raise InputError(file, f"made for another mesh ({mesh['num_vertices']} vertices) than {dataset.path} "
                             f"({dataset.num_vertices} vertices, or different faces/uv)")
        if self.meta["pose_dim"] != dataset.poses.shape[1]:
            raise InputError(file, f"expects {self.meta['pose_dim']}-dimensional poses, {dataset.path} has "
                             f"{dataset.poses.shape[1]}")


def load_corrector(path: str | os.PathLike) -> LoadedCorrector:
    """Open a geometry model directory written by `train_geometry`; InputError naming
    config.json or model.safetensors when either is missing, malformed or does not match
    the other (sizes are checked before anything is allocated; nothing is unpickled)."""

    path = as_path(path, "path")
    if not path.is_dir():
        raise InputError(path, "model directory not found")
    file = path / "config.json"
    meta = read_json(file)
    if not isinstance(meta, dict) or meta.get("format") != GEOMETRY_FORMAT:
        kind = meta.get("format") if isinstance(meta, dict) else None
        raise InputError(file, f'not a geometry model (format must be "{GEOMETRY_FORMAT}", got {kind!r}'
                         + ("; a per-camera model is read by predict" if kind == "mvtex-tsnn" else "") + ")")
    if meta.get("version") != GEOMETRY_VERSION:
        raise InputError(file, f"unsupported version {meta.get('version')!r} (readable: {GEOMETRY_VERSION})")
    mesh = meta.get("mesh")
    if not (isinstance(mesh, dict) and type(mesh.get("num_vertices")) is int and isinstance(mesh.get("base_mesh"), str)
            and type(meta.get("pose_dim")) is int):
        raise InputError(file, "missing or malformed 'mesh' or 'pose_dim'")
    try:
        config = CorrectorConfig.from_dict(meta.get("architecture") if isinstance(meta.get("architecture"), dict)
                                           else {})
        with torch.device("meta"):
            expected = GeometryCorrector(config).state_dict()
    except (TypeError, ValueError, OverflowError) as err:
        raise InputError(file, f"bad 'architecture' ({err})") from None
    if config.num_vertices != mesh["num_vertices"] or config.pose_dim != meta["pose_dim"]:
        raise InputError(file, "'architecture' does not match 'mesh' and 'pose_dim'")
    weights = path / "model.safetensors"
    state = read_weights(weights)
    if set(state) != set(expected) or any(state[k].shape != expected[k].shape or state[k].dtype != expected[k].dtype
                                          for k in expected):
        raise InputError(weights, "does not match the architecture in config.json")
    if not all(bool(torch.isfinite(v).all()) for v in state.values() if v.is_floating_point()):
        raise InputError(weights, "NaN or infinite values")
    model = GeometryCorrector(config)
    model.load_state_dict(state)
    model.eval()
    return LoadedCorrector(path=path, meta=meta, model=model)
