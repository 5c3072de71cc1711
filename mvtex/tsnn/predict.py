"""Trained networks -> a texcoord set (DESIGN §4, "source": "tsnn").

The texcoord set's mesh is the one the networks were trained on, rebuilt from the dataset
mesh and the models' subdivision level; every displacement is the network's image read at
the vertex's T_G (bilinear) — or, for `gp`, predicted at the vertex directly — and `assigned`
is all True (a prediction has no ray). A model that reports its predictive uncertainty
(`gp`) also writes `<camera>/uncertainty.npy`, the standard deviation of d per vertex.

A one-camera model (`paper`, `gp`, or `unet` trained with a camera name) predicts its camera. A camera-conditioned model predicts the cameras of
a rig, any camera (its view of the inferred mesh is an input), or without a rig the
cameras it was trained on.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from mvtex.data.camera import MAX_COORDINATE_M, check_camera_name
from mvtex.data.rig import save_rig
from mvtex.data.texcoords import (MAX_DISPLACEMENT, RIG_FILE, UNCERTAINTY_DTYPE, check_uncertainty, dataset_record,
                                  rig_record, write_header)
from mvtex.tsnn.atlas import AtlasSampler, sample_atlas, vertex_grid
from mvtex.tsnn.geometry import geometry_images
from mvtex.tsnn.modeldir import MODEL_FORMAT, READABLE_VERSIONS, made_for_mesh, rebuild_mesh
from mvtex.data.limits import MAX_SUBDIV
from mvtex.tsnn.options import MAX_RESOLUTION, MAX_WIDTH
from mvtex.util.errors import InputError, OptionError
from mvtex.util.files import create_npy, read_json, write_npy_rows
from mvtex.util.output import atomic_path, writer

_BLOCK = 256  # poses predicted (and written) at a time


@dataclass
class LoadedModel:
    """A model directory opened for inference.

    Attributes:
        path: the directory. meta: config.json.
        camera: its camera name; None for a camera-conditioned model.
        cameras: the training cameras, name -> (3,4) cam_from_world (None for a one-camera
            model, whose camera is implicit).
        network: the `TSNN`, `UNet` or `PoseGP` in eval mode on the CPU.
    """

    path: Path
    camera: str | None
    meta: dict[str, Any]
    network: Any
    cameras: dict[str, Any] | None = None

    @property
    def subdiv(self) -> int:
        return int(self.meta["mesh"]["subdiv"])

    @property
    def conditioned(self) -> bool:
        """True when the network takes the camera as an input (serves any camera)."""
        return bool(getattr(self.network.config, "view", False))

    @property
    def needs_geometry(self) -> bool:
        return hasattr(self.network, "geometry_mean")


def _require(meta: dict, file: Path, key: str, kind: type | tuple[type, ...]):
    value = meta.get(key)
    if not isinstance(value, kind):
        raise InputError(file, f"missing or malformed '{key}'")
    return value


def load_model(path: str | os.PathLike) -> LoadedModel:
    """Open a model directory written by `mvtex.tsnn.train.train`.

    Raises:
        InputError: naming config.json or model.safetensors when either is missing,
            malformed, or does not match the other.
    """
    import torch
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    from mvtex.tsnn.model import build_network

    from mvtex.util.checks import as_path

    path = as_path(path, "path")
    if not path.is_dir():
        raise InputError(path, "model directory not found")
    file = path / "config.json"
    meta = read_json(file)
    if not isinstance(meta, dict) or meta.get("format") != MODEL_FORMAT:
        raise InputError(file, f'not a TSNN model (format must be "{MODEL_FORMAT}")')
    if meta.get("version") not in READABLE_VERSIONS:
        raise InputError(file, f"unsupported version {meta.get('version')!r} "
                         f"(readable: {', '.join(map(str, READABLE_VERSIONS))})")
    camera = meta.get("camera")
    if not (camera is None or isinstance(camera, str)):
        raise InputError(file, "malformed 'camera' (a name, or null for a camera-conditioned model)")
    if camera is not None:
        try:
            check_camera_name(camera)
        except ValueError as err:
            raise InputError(file, str(err)) from None
    arch = _require(meta, file, "architecture", dict)
    mesh = _require(meta, file, "mesh", dict)
    for key in ("subdiv", "num_base_vertices", "num_vertices"):
        if not isinstance(mesh.get(key), int) or isinstance(mesh.get(key), bool) or mesh[key] < 0:
            raise InputError(file, f"missing or malformed 'mesh.{key}'")
    if not isinstance(mesh.get("base_mesh", mesh.get("base_mesh_sha256")), str):
        raise InputError(file, "missing or malformed 'mesh.base_mesh'")
    if mesh["subdiv"] > MAX_SUBDIV:
        raise InputError(file, f"mesh.subdiv is {mesh['subdiv']}, at most {MAX_SUBDIV} is supported")
    # Sizes are checked, and the network built on the "meta" device (no memory), before the
    # weights file is read: config.json cannot make us allocate more than the file holds.
    widths = arch.get("widths") if isinstance(arch.get("widths"), (list, tuple)) else ()
    sizes = [arch.get("resolution"), arch.get("width"), arch.get("min_width"), *widths]
    if any(isinstance(v, (int, float)) and not isinstance(v, bool) and v > limit
           for v, limit in zip(sizes, [MAX_RESOLUTION] + [MAX_WIDTH] * (len(sizes) - 1))):
        raise InputError(file, f"architecture too large (resolution at most {MAX_RESOLUTION}, "
                         f"channels at most {MAX_WIDTH})")
    try:
        with torch.device("meta"):
            network = build_network(arch)
    except (TypeError, ValueError, OverflowError) as err:
        raise InputError(file, f"bad 'architecture' ({err})") from None
    conditioned = bool(getattr(network.config, "view", False))
    if conditioned == (camera is not None):
        raise InputError(file, "'camera' must be null exactly when the architecture is conditioned on the view")
    cameras = None
    if conditioned:
        raw = meta.get("cameras")
        try:
            cameras = {str(k): np.asarray(v, dtype=np.float64) for k, v in raw.items()}
        except (AttributeError, TypeError, ValueError):
            cameras = None
        if not cameras or any(v.shape != (3, 4) or not np.all(np.isfinite(v)) or np.abs(v).max() > MAX_COORDINATE_M
                              for v in cameras.values()):
            raise InputError(file, "'cameras' must map camera names to finite 3x4 cam_from_world matrices (entries "
                             f"at most {MAX_COORDINATE_M:g} in magnitude)")
    if hasattr(network, "geometry_mean"):  # the U-Net rebuilds its input images: it needs the atlas
        dilation = meta.get("atlas", {}).get("dilation") if isinstance(meta.get("atlas"), dict) else None
        if not isinstance(dilation, int) or isinstance(dilation, bool) or not 0 <= dilation <= 64:
            raise InputError(file, "missing or malformed 'atlas.dilation'")
    weights = path / "model.safetensors"
    if not weights.is_file():
        raise InputError(weights, "file not found")
    try:
        state = load_file(str(weights), device="cpu")
    except (SafetensorError, OSError, ValueError, MemoryError) as err:
        raise InputError(weights, f"not a readable safetensors file ({err})") from None
    expected = network.state_dict()
    optional = set(getattr(network, "optional_buffers", ()))  # a model stored before they existed
    missing = sorted(set(expected) - set(state) - optional)
    unexpected = sorted(set(state) - set(expected))
    if missing or unexpected:
        raise InputError(weights, f"does not match the architecture in config.json "
                         f"(missing {missing[:3]}, unexpected {unexpected[:3]})")
    bad = [k for k in expected if k in state and expected[k].shape != state[k].shape]
    if bad:
        raise InputError(weights, f"tensor {bad[0]!r} has shape {tuple(state[bad[0]].shape)}, the architecture in "
                         f"config.json needs {tuple(expected[bad[0]].shape)}")
    if not all(torch.isfinite(v).all() for v in state.values() if v.is_floating_point()):
        raise InputError(weights, "NaN or infinite weights")
    network = build_network(arch)
    network.load_state_dict({**network.state_dict(), **state})  # optional buffers absent: their defaults
    network.eval()
    return LoadedModel(path=path, camera=camera, meta=meta, network=network, cameras=cameras)


def predict_displacements(model: LoadedModel, poses: np.ndarray, uv: np.ndarray, *, geometry: np.ndarray | None = None,
                          cam_from_world: np.ndarray | None = None, batch_size: int = 32,
                          device: str = "cpu") -> np.ndarray:
    """Per-vertex displacements of one network for one camera.

    Args:
        model: from `load_model`.
        poses: (K,P) float pose vectors.
        uv: (n',2) T_G of the vertices to read.
        geometry: (K,G,R,R) geometry images of the poses (`mvtex.tsnn.geometry`); `unet` only.
        cam_from_world: (3,4) extrinsics of the camera; camera-conditioned models only.

    Returns:
        (K,n',2) float32 d.
    """
    import torch

    net = model.network.to(device)
    if getattr(net, "per_vertex", False):  # `gp`: d at the vertices, no atlas image
        if len(uv) != net.config.num_vertices:
            raise InputError(model.path / "config.json", f"predicts {net.config.num_vertices} vertices, "
                             f"the mesh has {len(uv)}")
        with torch.no_grad():
            return net(torch.from_numpy(np.array(poses, dtype=np.float64)).to(device)).cpu().numpy()
    grid = vertex_grid(uv).to(device)
    x = torch.from_numpy(np.array(poses, dtype=np.float32)).to(device)
    cam = None if cam_from_world is None else torch.tensor(np.asarray(cam_from_world, np.float32), device=device)
    out = np.empty((len(x), len(uv), 2), dtype=np.float32)
    with torch.no_grad():
        for start in range(0, len(x), batch_size):
            xb = x[start:start + batch_size]
            if model.needs_geometry:
                g = torch.from_numpy(geometry[start:start + batch_size]).to(device)
                images = net(xb, g, None if cam is None else cam.expand(len(xb), -1, -1))
            else:
                images = net(xb)
            out[start:start + len(images)] = sample_atlas(images, grid).cpu().numpy()
    return out


def check_prediction(displacement: np.ndarray, model: LoadedModel, camera: str, poses: Sequence[int]) -> None:
    """Refuse (InputError naming the model's weights) a prediction that is not a texcoord
    perturbation: NaN or infinite values, or |d| above `MAX_DISPLACEMENT` (the whole
    atlas). A model whose weights are finite can still overflow on some poses; its output
    must never reach a texcoord set.

    Args:
        displacement: (k,n',2) the model's d for `poses` of `camera`.
    """
    d = np.asarray(displacement, dtype=np.float64)
    finite = np.isfinite(d).all(axis=(1, 2))
    with np.errstate(invalid="ignore", over="ignore"):
        length = np.sqrt((np.where(np.isfinite(d), d, 0.0) ** 2).sum(axis=2)).max(axis=1, initial=0.0)
    bad = ~finite | (length > MAX_DISPLACEMENT)
    if bad.any():
        row = int(np.argmax(bad))
        what = "NaN or infinite displacements" if not finite[row] else \
            f"a displacement of length {length[row]:.4g} uv units (more than {MAX_DISPLACEMENT}, the whole atlas)"
        raise InputError(model.path / "model.safetensors", f"predicts {what} for camera {camera!r} at pose "
                         f"{int(poses[row])}: the model is broken; train it again")


def predict_uncertainty(model: LoadedModel, poses: np.ndarray, uv: np.ndarray, device: str = "cpu"
                        ) -> np.ndarray | None:
    """Per-vertex predictive standard deviation of a model's displacements, where the
    model reports one (`gp` models; `mvtex.tsnn.gp.PoseGP.predictive_std`).

    Args:
        model: from `load_model`.
        poses: (K,P) float pose vectors.
        uv: (n',2) T_G of the vertices.

    Returns:
        (K,n') float32 in uv units (the root of the expected squared length of d's error),
        or None for a model that reports no uncertainty.
    """
    import torch

    net = model.network.to(device)
    if not getattr(net, "per_vertex", False) or not getattr(net, "has_uncertainty", False):
        return None
    if len(uv) != net.config.num_vertices:
        raise InputError(model.path / "config.json", f"predicts {net.config.num_vertices} vertices, "
                         f"the mesh has {len(uv)}")
    with torch.no_grad():
        std = net.predictive_std(torch.from_numpy(np.array(poses, dtype=np.float64)).to(device))
    if std is None:
        return None
    with np.errstate(over="ignore", invalid="ignore"):  # beyond float32's range: inf, which `check_uncertainty` refuses
        return std.cpu().numpy().astype(UNCERTAINTY_DTYPE)


def _jobs(loaded: list[LoadedModel], rig) -> list[tuple[str, LoadedModel, np.ndarray | None]]:
    """(camera name, model, cam_from_world or None) for every camera to predict."""
    jobs: dict[str, tuple[LoadedModel, np.ndarray | None]] = {}

    def add(name: str, model: LoadedModel, view):
        if name in jobs:
            raise InputError(model.path / "config.json", f"camera {name!r} is also predicted by {jobs[name][0].path}")
        jobs[name] = (model, view)

    for m in loaded:  # one-camera models first: they predict their own camera
        if not m.conditioned:
            if rig is None or m.camera in rig.names:
                add(m.camera, m, None)
    for m in loaded:
        if m.conditioned:
            cams = {c.name: c.cam_from_world for c in rig} if rig is not None else m.cameras
            for name, view in cams.items():
                if name not in jobs or jobs[name][0].conditioned:
                    add(name, m, view)
    if not jobs:
        raise InputError(loaded[0].path / "config.json", "predicts none of the rig's cameras "
                         f"({', '.join(rig.names) if rig is not None else ''})")
    return [(name, m, view) for name, (m, view) in jobs.items()]


@writer("predict", inputs=lambda a: (a["dataset"], a["models"]))
def predict(dataset, models: Sequence[str | os.PathLike], out: str | os.PathLike, *, poses: Sequence[int],
            rig=None, progress: bool = True, device: str = "cpu", overwrite: bool = False) -> Path:
    """Run networks over poses and write a texcoord set.

    Args:
        dataset: the `mvtex.data.dataset.Dataset` (its mesh, inferred meshes and pose vectors).
        models: model directories (same subdivision level): one-camera models and/or a
            camera-conditioned one.
        out: texcoord set directory to write (atomically).
        poses: dataset pose indices, in the order of the set's rows.
        rig: a `mvtex.data.rig.Rig`: predict its cameras (a one-camera model serves its own
            camera, a camera-conditioned model every other camera of the rig). None: every
            model's own camera(s).
        progress: progress bar over cameras on stderr.
        device: where to run the networks.
        overwrite: replace another command's output at `out` (never files mvtex did not
            write, never an input: the writer policy of `mvtex.util.output`).

    Returns:
        `out` as a Path.

    Raises:
        InputError: a malformed model, models of different subdivision levels, two models
            for one camera, a model made for another mesh or pose size, a rig camera no
            model can predict.
    """
    from mvtex.data.dataset import as_dataset
    from mvtex.data.rig import as_rig
    from mvtex.util.checks import as_path

    dataset = as_dataset(dataset)
    out = as_path(out, "out")
    rig = None if rig is None else as_rig(rig)
    if isinstance(models, (str, os.PathLike)):
        models = [models]
    if not hasattr(models, "__iter__") or isinstance(models, (bytes, dict)):
        raise OptionError("models", f"must be a list of model folder paths, got {type(models).__name__}")
    models = [as_path(m, "models") for m in models]
    from tqdm import tqdm

    out = Path(out)
    if not models:
        raise InputError(out, "no model given")
    poses = dataset.check_poses(poses)
    loaded = [load_model(m) for m in models]
    first = loaded[0]
    for m in loaded:
        cfg = m.path / "config.json"
        if m.subdiv != first.subdiv:
            raise InputError(cfg, f"subdivision level {m.subdiv} differs from {first.path} ({first.subdiv}); "
                             "one texcoord set has one mesh: predict models of one level together")
        if m.meta["mesh"]["num_base_vertices"] != dataset.num_vertices or \
                not made_for_mesh(m.meta["mesh"], dataset.faces, dataset.uv):
            raise InputError(cfg, f"made for another mesh ({m.meta['mesh']['num_base_vertices']} vertices) than "
                             f"{dataset.path} ({dataset.num_vertices} vertices, or different faces/uv)")
        if m.network.config.pose_dim != dataset.poses.shape[1]:
            raise InputError(cfg, f"expects {m.network.config.pose_dim}-dimensional poses, "
                             f"{dataset.path} has {dataset.poses.shape[1]}")
    jobs = _jobs(loaded, rig)
    if rig is not None:
        unserved = [c for c in rig.names if c not in {name for name, _, _ in jobs}]
        if unserved:
            raise InputError(out, f"no model predicts camera(s) {', '.join(unserved)} of the rig: give a model "
                             "per camera or a camera-conditioned one")
    faces, uv, parent = rebuild_mesh(dataset.faces, dataset.uv, first.subdiv)
    if len(uv) != first.meta["mesh"]["num_vertices"]:
        raise InputError(first.path / "config.json", f"mesh.num_vertices {first.meta['mesh']['num_vertices']} but "
                         f"the dataset mesh subdivided {first.subdiv} time(s) has {len(uv)}")
    x = np.asarray(dataset.poses[poses], dtype=np.float32).reshape(len(poses), -1)
    samplers: dict[tuple[int, int], AtlasSampler] = {}  # (resolution, dilation) -> the models' atlas
    names = [name for name, _, _ in jobs]
    # Block by block of poses, written into the files as they come: memory stays that of
    # one block (d of 10,000 poses and 24k vertices is 1.9 GB per camera).
    with atomic_path(out) as tmp, tqdm(total=len(poses) * len(jobs), desc="predict", unit="image",
                                       disable=not progress) as bar:
        tmp.mkdir()
        record = {"dataset": dataset_record(dataset), "models": {name: str(m.path) for name, m, _ in jobs}}
        if rig is not None:
            record["rig"] = rig_record(rig.select(names))
            save_rig(rig.select(names), tmp / RIG_FILE)  # the set records its cameras: --rig defaults to them
        write_header(tmp, faces=faces, uv=uv, parent=parent, source="tsnn", subdiv=first.subdiv, poses=poses,
                     cameras=names, **record)
        uncertain = {name for name, m, _ in jobs if getattr(m.network, "has_uncertainty", False)}
        for name in names:
            (tmp / name).mkdir()
            create_npy(tmp / name / "displacement.npy", np.float32, (len(poses), len(uv), 2))
            create_npy(tmp / name / "assigned.npy", np.bool_, (len(poses), len(uv)))
            if name in uncertain:
                create_npy(tmp / name / "uncertainty.npy", np.float32, (len(poses), len(uv)))
        for start in range(0, len(poses), _BLOCK):
            rows = poses[start:start + _BLOCK]
            index = range(start, start + len(rows))
            geometry: dict[tuple[int, int], np.ndarray] = {}
            for name, m, view in jobs:
                g = None
                if m.needs_geometry:
                    key = (m.network.config.resolution, int(m.meta["atlas"]["dilation"]))
                    if key not in geometry:
                        if key not in samplers:
                            samplers[key] = AtlasSampler(faces, uv, key[0], dilation=key[1], source=m.path)
                        geometry[key] = geometry_images(dataset, rows, samplers[key], parent)
                    g = geometry[key]
                d = predict_displacements(m, x[start:start + len(rows)], uv, geometry=g, cam_from_world=view,
                                          device=device)
                check_prediction(d, m, name, rows)
                write_npy_rows(tmp / name / "displacement.npy", index, d)
                write_npy_rows(tmp / name / "assigned.npy", index, np.ones((len(rows), len(uv)), dtype=bool))
                if name in uncertain:
                    std = predict_uncertainty(m, x[start:start + len(rows)], uv, device=device)
                    check_uncertainty(std, (len(rows), len(uv)), lambda problem, row: InputError(
                        m.path / "model.safetensors", f"predicts {problem} for camera {name!r}"
                        + ("" if row is None else f" at pose {int(rows[row])}") + ": the model is broken; train it again"))
                    write_npy_rows(tmp / name / "uncertainty.npy", index, std)
                bar.update(len(rows))
    return out
