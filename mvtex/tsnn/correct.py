"""`mvtex correct`: a dataset whose inferred mesh is the geometry corrector's (DESIGN §4, §5).

The corrected set is an ordinary dataset: texture sliding, per-camera models, `eval` and
`triangulate` run on it as on any other. Its inferred.npy is the corrected mesh,
inferred + f r(θ) (`mvtex.tsnn.corrector`; a training pose of the model gets its
out-of-sample r, so models stacked on the set see the errors they meet at run time), where
the corrector is unsure shrunk per vertex by f = ‖r‖² / (‖r‖² + κσ²) (`CorrectOptions`),
and its σ is that of the shrunk correction, sqrt(σ² + (1 - f)² ‖r‖²). It keeps what makes
it self-contained and traceable:

    original_inferred.npy     (K,n,3) float32 the mesh before the correction: the source's
                              inferred mesh (or the source's own original_inferred.npy,
                              when the source was corrected already)
    geometry_uncertainty.npy  (K,n) float32 the corrector's σ per vertex, in meters
    dataset.json "correction" {"model", "model_dataset", "source": {"path", "name",
                              "content"}, "source_poses", "out_of_sample_poses",
                              "sigma_scale", "options"}

gt.npy, the body and the split are the source's (gt only when the source has it: without
it the corrected set is an inference set); rows are the source's selected poses, in order.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from tqdm import tqdm

from mvtex.data.dataset import ORIGINAL_FILE, UNCERTAINTY_FILE, as_dataset, content_fingerprint, metadata
from mvtex.data.mesh import rms_distance
from mvtex.tsnn.corrector import load_corrector
from mvtex.tsnn.options import CorrectOptions
from mvtex.util.checks import as_path, check_instance
from mvtex.util.errors import InputError
from mvtex.util.files import create_npy, read_row, write_npy_rows
from mvtex.util.output import atomic_path, writer

_BLOCK = 256  # poses corrected and written at a time


def shrink_correction(residual: np.ndarray, sigma: np.ndarray, shrink: float) -> tuple[np.ndarray, np.ndarray]:
    """The correction kept where the corrector is unsure, and its standard deviation.

    Args:
        residual: (B,n,3) predicted r. sigma: (B,n) its σ. shrink: κ ≥ 0.

    Returns:
        f r (B,n,3) with f = ‖r‖² / (‖r‖² + κσ²) (1 where both are 0), and (B,n)
        sqrt(σ² + (1 - f)² ‖r‖²): the expected error of f r when the truth is r ± σ.
    """
    r2 = np.sum(residual ** 2, axis=-1)
    if not shrink:
        return residual, sigma
    with np.errstate(invalid="ignore", divide="ignore"):
        f = np.where(r2 > 0, r2 / (r2 + shrink * sigma ** 2), 1.0)
    return residual * f[..., None], np.sqrt(sigma ** 2 + (1 - f) ** 2 * r2)


@dataclass(frozen=True)
class CorrectResult:
    """What `correct` wrote (`mvtex correct --json` is `to_json()`).

    Attributes:
        out: the corrected set. poses: its number of poses. out_of_sample_poses: how many of
            them are training poses of the model (corrected out of sample).
        has_gt: whether the set has gt (the source had it).
        rmse_m: with gt, the mean over poses of the all-vertex RMSE to gt, {"original",
            "corrected"}; None without gt.
        mean_sigma_m: the mean predicted σ per vertex.
    """

    out: str
    poses: int
    out_of_sample_poses: int
    has_gt: bool
    rmse_m: dict[str, float] | None
    mean_sigma_m: float

    def to_json(self) -> dict:
        return {"out": self.out, "poses": self.poses, "out_of_sample_poses": self.out_of_sample_poses,
                "has_gt": self.has_gt, "rmse_m": self.rmse_m, "mean_sigma_m": self.mean_sigma_m}


def _remap_split(split: dict[str, list[int]], poses: list[int]) -> dict[str, list[int]]:
    row = {p: i for i, p in enumerate(poses)}
    return {k: [row[int(p)] for p in split[k] if int(p) in row] for k in ("train", "val", "test")}


@writer("correct", inputs=lambda a: (a["dataset"], a["model"]))
def correct(dataset, model: str | os.PathLike, out: str | os.PathLike, *, poses: Sequence[int] | None = None,
            options: CorrectOptions = CorrectOptions(), progress: bool = True,
            overwrite: bool = False) -> CorrectResult:
    """Write the corrected set of a dataset (`mvtex correct DATA --model GEOM --out DATA2`).

    Args:
        dataset: a `mvtex.data.dataset.Dataset` or its directory (with or without gt).
        model: a geometry model directory (`mvtex.tsnn.corrector.train_geometry`) made for
            this mesh and pose size.
        out: the dataset directory to write (atomically).
        poses: the source's poses to correct, in the order of the set's rows (default all).
        options: see `CorrectOptions`.
        progress: a progress bar on stderr.
        overwrite: replace another command's output at `out` (the writer policy).

    Returns:
        A `CorrectResult`.

    Raises:
        InputError: a model made for another mesh or pose size, a pose out of range, a
            correction that is not finite.
    """

    check_instance(options, CorrectOptions, "options")
    dataset = as_dataset(dataset)
    model = as_path(model, "model")
    out = Path(as_path(out, "out"))
    poses = list(range(dataset.num_poses)) if poses is None else dataset.check_poses(poses)
    loaded = load_corrector(model)
    loaded.check_dataset(dataset)
    has_gt = dataset.has_gt
    source_original = dataset.original_inferred if dataset.corrected else dataset.inferred
    n, k = dataset.num_vertices, len(poses)
    x = np.asarray(dataset.poses[poses], np.float32).reshape(k, -1)
    seen = 0
    rmse = {"original": [], "corrected": []}
    sigma_sum = 0.0
    with atomic_path(out) as tmp, tqdm(total=k, desc="correct", unit="pose", disable=not progress,
                                       file=sys.stderr) as bar:
        tmp.mkdir()
        arrays = {"inferred.npy": ((k, n, 3), np.float32), ORIGINAL_FILE: ((k, n, 3), np.float32),
                  UNCERTAINTY_FILE: ((k, n), np.float32)}
        if has_gt:
            arrays["gt.npy"] = ((k, n, 3), np.float32)
        if dataset.body is not None:
            arrays["body.npy"] = ((k, dataset.body.num_vertices, 3), np.float32)
        for name, (shape, dtype) in arrays.items():
            create_npy(tmp / name, dtype, shape)
        for start in range(0, k, _BLOCK):
            rows = poses[start:start + _BLOCK]
            index = range(start, start + len(rows))
            residual, sigma, in_sample = loaded.model.predict(x[start:start + len(rows)])
            residual, sigma = shrink_correction(residual, sigma, options.shrink)
            inferred = np.stack([read_row(dataset.inferred, p) for p in rows]).astype(np.float64)
            corrected = (inferred + residual).astype(np.float32)
            if not (np.all(np.isfinite(corrected)) and np.all(np.isfinite(sigma))):
                raise InputError(loaded.path / "model.safetensors", "predicts NaN or infinite corrections: "
                                 "the model is broken; train it again")
            seen += int(in_sample.sum())
            sigma_sum += float(sigma.mean(axis=1).sum())
            write_npy_rows(tmp / "inferred.npy", index, corrected)
            original = np.stack([read_row(source_original, p) for p in rows])
            write_npy_rows(tmp / ORIGINAL_FILE, index, original)
            write_npy_rows(tmp / UNCERTAINTY_FILE, index, sigma.astype(np.float32))
            if has_gt:
                gt = np.stack([read_row(dataset.gt, p) for p in rows])
                write_npy_rows(tmp / "gt.npy", index, gt)
                for g, o, c in zip(gt, original, corrected):
                    rmse["original"].append(rms_distance(o, g))
                    rmse["corrected"].append(rms_distance(c, g))
            if dataset.body is not None:
                write_npy_rows(tmp / "body.npy", index, np.stack([read_row(dataset.body.positions, p) for p in rows]))
            bar.update(len(rows))
        np.save(tmp / "poses.npy", x, allow_pickle=False)
        shutil.copyfile(Path(dataset.path) / "mesh.npz", tmp / "mesh.npz")
        if dataset.body is not None:
            shutil.copyfile(Path(dataset.path) / "body.npz", tmp / "body.npz")
        (tmp / "split.json").write_text(json.dumps(_remap_split(dataset.split, poses)) + "\n")
        record = {"model": str(loaded.path.resolve()), "model_dataset": loaded.meta.get("dataset"),
                  "source": {"path": str(Path(dataset.path).resolve()), "name": dataset.name,
                             "content": content_fingerprint(dataset) if has_gt else None},
                  "source_poses": [int(p) for p in poses], "out_of_sample_poses": seen,
                  "sigma_scale": float(loaded.model.sigma_scale), "options": asdict(options)}
        body = dataset.body
        meta = metadata(dataset.name, k, n, x.shape[1], None if body is None else body.faces,
                        None if body is None else body.positions, ground_truth=has_gt,
                        correction=record)  # the body's sizes
        (tmp / "dataset.json").write_text(json.dumps(meta, indent=2) + "\n")
    return CorrectResult(out=str(out), poses=k, out_of_sample_poses=seen, has_gt=has_gt,
                         rmse_m={key: float(np.mean(v)) for key, v in rmse.items()} if has_gt else None,
                         mean_sigma_m=sigma_sum / max(k, 1))
