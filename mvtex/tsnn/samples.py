"""Training samples of a texture sliding model and their losses: (pose, camera) pairs of a
texcoord set as tensors (`Samples`), one camera's displacements read a block of poses at a
time (`DisplacementRows`), a network run on samples whatever its architecture (`Forward`),
and the weighted MSE of d (`weighted_mse`, `sample_losses`).
"""

from __future__ import annotations

import math

import numpy as np

from mvtex.util.errors import InputError


class Samples:
    """Targets of (pose, camera) samples of one split, as tensors on the training device.

    Attributes:
        x: (S,P) pose vectors. d: (S,n',2) targets. w: (S,n') loss weights. assigned:
            (S,n') bool, where d came from the ray (the vertices the camera sees).
        pose_row: (S,) index of the sample's pose in `poses` (and in `geometry`).
        camera: (S,) index of the sample's camera in the trainer's camera list.
        geometry: (K,G,R,R) geometry images of `poses` (unet only) or None.
    """

    def __init__(self, dataset, texcoords, cameras: list[str], poses: list[int], weight_assigned: float, device,
                 geometry=None):
        import torch  # noqa: PLC0415 (loaded on use)

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
        self.assigned = torch.from_numpy(a).to(device)
        self.geometry = None if geometry is None else torch.from_numpy(geometry).to(device)

    def __len__(self) -> int:
        return len(self.d)


class Forward:
    """Runs a network on samples of a `Samples`, whatever its architecture."""

    def __init__(self, model, cam_from_world=None):
        self.model = model
        self.cam_from_world = cam_from_world  # (C,3,4) tensor of the trainer's cameras, or None

    def __call__(self, data: Samples, idx, poses=None):
        x = data.x[idx] if poses is None else poses
        if not hasattr(self.model, "geometry_mean"):  # the paper's decoder: the pose alone
            return self.model(x)
        cams = self.cam_from_world[data.camera[idx]] if self.model.config.view else None
        return self.model(x, data.geometry[data.pose_row[idx]], cams)


def weighted_mse(pred, target, weight):
    return ((pred - target).square().sum(-1) * weight).sum() / weight.sum()


def sample_losses(predict, data: Samples, batch_size: int) -> dict[str, float]:
    """Weighted MSE ("loss"), unweighted RMSE ("rmse") and the zero predictor's weighted MSE
    ("zero_loss") over a sample set; and over the vertices the camera sees (`Samples.assigned`,
    every vertex where it sees none) the gain g ≥ 0 of the predictions that minimises the
    squared error of g times them ("gain": Σ p·d / Σ p·p, 1 where every prediction is 0;
    `TrainOptions.gain`) and that mean squared error per vertex ("gain_loss").

    Args:
        predict: (data, idx) -> (len(idx),n',2) per-vertex d of those samples (model in eval mode).
    """
    import torch  # noqa: PLC0415 (loaded on use)

    if len(data) == 0:
        return {}
    se_w = w_sum = se = zero_w = 0.0
    seen = data.assigned if bool(data.assigned.any()) else torch.ones_like(data.assigned)
    cross = square = target = 0.0  # Σ p·d, Σ p·p, Σ d·d over the vertices seen
    with torch.no_grad():
        for start in range(0, len(data), batch_size):
            idx = torch.arange(start, min(start + batch_size, len(data)), device=data.d.device)
            pred = predict(data, idx)
            e = (pred - data.d[idx]).square().sum(-1)
            se_w += float((e * data.w[idx]).sum())
            w_sum += float(data.w[idx].sum())
            se += float(e.sum())
            zero_w += float((data.d[idx].square().sum(-1) * data.w[idx]).sum())
            mask = seen[idx]
            cross += float((pred * data.d[idx]).sum(-1)[mask].sum())
            square += float(pred.square().sum(-1)[mask].sum())
            target += float(data.d[idx].square().sum(-1)[mask].sum())
    n = len(data) * data.d.shape[1]
    gain = max(cross, 0.0) / square if square > 0 else 1.0
    gain_loss = (gain * gain * square - 2.0 * gain * cross + target) / int(seen.sum())
    return {"loss": se_w / w_sum, "rmse": math.sqrt(se / n), "zero_loss": zero_w / w_sum, "gain": gain,
            "gain_loss": max(gain_loss, 0.0)}


class DisplacementRows:
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
