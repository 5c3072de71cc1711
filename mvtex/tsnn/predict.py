"""Trained camera networks -> a texcoord set (DESIGN §4, "source": "tsnn").

The texcoord set's mesh is the one the networks were trained on, rebuilt from the dataset
mesh and the models' subdivision level; every displacement is the network's image read at
the vertex's T_G (bilinear), and `assigned` is all True (a prediction has no ray).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..camera import check_camera_name
from ..errors import InputError
from ..io import read_json
from ..texcoords import save_texcoords
from .train import MAX_RESOLUTION, MAX_SUBDIV, MAX_WIDTH, MODEL_FORMAT, MODEL_VERSION, mesh_fingerprint, rebuild_mesh


@dataclass
class LoadedModel:
    """A model directory opened for inference.

    Attributes:
        path: the directory. camera: its camera name. meta: config.json.
        network: the `TSNN` in eval mode on the CPU.
    """

    path: Path
    camera: str
    meta: dict[str, Any]
    network: Any

    @property
    def subdiv(self) -> int:
        return int(self.meta["mesh"]["subdiv"])


def _require(meta: dict, file: Path, key: str, kind: type | tuple[type, ...]):
    value = meta.get(key)
    if not isinstance(value, kind):
        raise InputError(file, f"missing or malformed '{key}'")
    return value


def load_model(path: str | os.PathLike) -> LoadedModel:
    """Open a model directory written by `train_camera`.

    Raises:
        InputError: naming config.json or model.safetensors when either is missing,
            malformed, or does not match the other.
    """
    import torch
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    from .model import TSNN, ModelConfig

    path = Path(path)
    if not path.is_dir():
        raise InputError(path, "model directory not found")
    file = path / "config.json"
    meta = read_json(file)
    if not isinstance(meta, dict) or meta.get("format") != MODEL_FORMAT:
        raise InputError(file, f'not a TSNN model (format must be "{MODEL_FORMAT}")')
    if meta.get("version") != MODEL_VERSION:
        raise InputError(file, f"unsupported version {meta.get('version')!r} (expected {MODEL_VERSION})")
    camera = _require(meta, file, "camera", str)
    try:
        check_camera_name(camera)
    except ValueError as err:
        raise InputError(file, str(err)) from None
    arch = _require(meta, file, "architecture", dict)
    mesh = _require(meta, file, "mesh", dict)
    for key in ("subdiv", "num_base_vertices", "num_vertices"):
        if not isinstance(mesh.get(key), int) or isinstance(mesh.get(key), bool) or mesh[key] < 0:
            raise InputError(file, f"missing or malformed 'mesh.{key}'")
    # Checked before anything is built from it: each level multiplies the mesh by four.
    if mesh["subdiv"] > MAX_SUBDIV:
        raise InputError(file, f"mesh.subdiv is {mesh['subdiv']}, at most {MAX_SUBDIV} is supported")
    if not isinstance(mesh.get("base_mesh_sha256"), str):
        raise InputError(file, "missing or malformed 'mesh.base_mesh_sha256'")
    try:
        config = ModelConfig.from_dict(arch)
    except (TypeError, ValueError, OverflowError) as err:
        raise InputError(file, f"bad 'architecture' ({err})") from None
    if config.resolution > MAX_RESOLUTION or config.width > MAX_WIDTH or config.min_width > MAX_WIDTH:
        raise InputError(file, f"architecture too large (resolution {config.resolution}, width {config.width}; "
                         f"at most {MAX_RESOLUTION} and {MAX_WIDTH})")
    weights = path / "model.safetensors"
    if not weights.is_file():
        raise InputError(weights, "file not found")
    try:
        state = load_file(str(weights), device="cpu")
    except (SafetensorError, OSError, ValueError, MemoryError) as err:
        raise InputError(weights, f"not a readable safetensors file ({err})") from None
    # The architecture is built on the "meta" device (no memory) and compared with the
    # weights file first, so config.json cannot make us allocate more than the file holds.
    with torch.device("meta"):
        expected = TSNN(config).state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    if missing or unexpected:
        raise InputError(weights, f"does not match the architecture in config.json "
                         f"(missing {missing[:3]}, unexpected {unexpected[:3]})")
    bad = [k for k in expected if expected[k].shape != state[k].shape]
    if bad:
        raise InputError(weights, f"tensor {bad[0]!r} has shape {tuple(state[bad[0]].shape)}, the architecture in "
                         f"config.json needs {tuple(expected[bad[0]].shape)}")
    if not all(torch.isfinite(v).all() for v in state.values() if v.is_floating_point()):
        raise InputError(weights, "NaN or infinite weights")
    network = TSNN(config)
    network.load_state_dict(state)
    network.eval()
    return LoadedModel(path=path, camera=camera, meta=meta, network=network)


def predict_displacements(model: LoadedModel, poses: np.ndarray, uv: np.ndarray, *, batch_size: int = 32,
                          device: str = "cpu") -> np.ndarray:
    """Per-vertex displacements of one network.

    Args:
        model: from `load_model`.
        poses: (K,P) float pose vectors.
        uv: (n',2) T_G of the vertices to read.

    Returns:
        (K,n',2) float32 d.
    """
    import torch

    from .atlas import sample_atlas, vertex_grid

    net = model.network.to(device)
    grid = vertex_grid(uv).to(device)
    x = torch.from_numpy(np.array(poses, dtype=np.float32)).to(device)
    out = np.empty((len(x), len(uv), 2), dtype=np.float32)
    with torch.no_grad():
        for start in range(0, len(x), batch_size):
            images = net(x[start:start + batch_size])
            out[start:start + len(images)] = sample_atlas(images, grid).cpu().numpy()
    return out


def predict(dataset, models: Sequence[str | os.PathLike], out: str | os.PathLike, *, poses: Sequence[int],
            progress: bool = True, device: str = "cpu") -> Path:
    """Run one network per camera over poses and write a texcoord set.

    Args:
        dataset: the `mvtex.dataset.Dataset` (its mesh and pose vectors).
        models: model directories (one per camera, distinct cameras, same subdivision level).
        out: texcoord set directory to write (atomically).
        poses: dataset pose indices, in the order of the set's rows.
        progress: progress bar over cameras on stderr.
        device: where to run the networks.

    Returns:
        `out` as a Path.

    Raises:
        InputError: a malformed model, models of different subdivision levels or of the same
            camera, a model made for another mesh or pose size.
    """
    from tqdm import tqdm

    out = Path(out)
    if not models:
        raise InputError(out, "no model given")
    poses = dataset.check_poses(poses)
    loaded = [load_model(m) for m in models]
    first = loaded[0]
    fingerprint = mesh_fingerprint(dataset.faces, dataset.uv)
    seen: dict[str, Path] = {}
    for m in loaded:
        cfg = m.path / "config.json"
        if m.subdiv != first.subdiv:
            raise InputError(cfg, f"subdivision level {m.subdiv} differs from {first.path} ({first.subdiv}); "
                             "one texcoord set has one mesh: predict models of one level together")
        if m.camera in seen:
            raise InputError(cfg, f"camera {m.camera!r} is also predicted by {seen[m.camera]}")
        seen[m.camera] = m.path
        if m.meta["mesh"]["num_base_vertices"] != dataset.num_vertices or m.meta["mesh"]["base_mesh_sha256"] != fingerprint:
            raise InputError(cfg, f"made for another mesh ({m.meta['mesh']['num_base_vertices']} vertices) than "
                             f"{dataset.path} ({dataset.num_vertices} vertices, or different faces/uv)")
        if m.network.config.pose_dim != dataset.poses.shape[1]:
            raise InputError(cfg, f"expects {m.network.config.pose_dim}-dimensional poses, "
                             f"{dataset.path} has {dataset.poses.shape[1]}")
    faces, uv, parent = rebuild_mesh(dataset.faces, dataset.uv, first.subdiv)
    if len(uv) != first.meta["mesh"]["num_vertices"]:
        raise InputError(first.path / "config.json", f"mesh.num_vertices {first.meta['mesh']['num_vertices']} but "
                         f"the dataset mesh subdivided {first.subdiv} time(s) has {len(uv)}")
    x = np.asarray(dataset.poses[poses], dtype=np.float32).reshape(len(poses), -1)
    displacement, assigned = {}, {}
    for m in tqdm(loaded, desc="predict", unit="camera", disable=not progress):
        displacement[m.camera] = predict_displacements(m, x, uv, device=device)
        assigned[m.camera] = np.ones((len(poses), len(uv)), dtype=bool)
    return save_texcoords(out, faces=faces, uv=uv, parent=parent, source="tsnn", subdiv=first.subdiv, poses=poses,
                          displacement=displacement, assigned=assigned,
                          models={m.camera: str(m.path) for m in loaded})
