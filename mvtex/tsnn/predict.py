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
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from tqdm import tqdm

from mvtex.data.camera import Camera
from mvtex.data.dataset import as_dataset
from mvtex.data.rig import Rig, as_rig, save_rig
from mvtex.data.texcoords import (
    MAX_DISPLACEMENT,
    RIG_FILE,
    UNCERTAINTY_DTYPE,
    check_uncertainty,
    dataset_record,
    rig_record,
    write_header,
)
from mvtex.tsnn.atlas import AtlasSampler, sample_atlas, vertex_grid
from mvtex.tsnn.config import CONFIG_FILE, GEOMETRY_FILE, ModelConfig
from mvtex.tsnn.geometry import MeshGeometry, geometry_images
from mvtex.tsnn.model import build_network
from mvtex.tsnn.modeldir import read_weights, rebuild_mesh
from mvtex.util.checks import as_path
from mvtex.util.errors import InputError, OptionError
from mvtex.util.files import create_npy, load_npz, write_npy_rows
from mvtex.util.output import atomic_path, writer

_BLOCK = 256  # poses predicted (and written) at a time


@dataclass
class LoadedModel:
    """A model directory opened for inference.

    Attributes:
        path: the directory. config: its config.json (`ModelConfig`).
        network: the `TSNN`, `UNet`, `PoseGP` or `PoseMLP` in eval mode on the CPU.
        geometry: a `unet`'s geometry reference (`MeshGeometry.reference_arrays`, from
            geometry.npz), or None (other architectures; a `unet` stored without one
            measures against the set's rest shape).
    """

    path: Path
    config: ModelConfig
    network: Any
    geometry: dict[str, np.ndarray] | None = None

    @property
    def camera(self) -> str | None:
        """Its camera name; None for a camera-conditioned model."""
        return self.config.camera

    @property
    def cameras(self) -> dict[str, np.ndarray] | None:
        """The training cameras of a camera-conditioned model, name -> (3,4) cam_from_world;
        None for a one-camera model (its camera is implicit)."""
        return dict(self.config.cameras) if self.conditioned else None

    @property
    def meta(self) -> dict[str, Any]:
        """config.json as a dict."""
        return self.config.to_json()

    @property
    def subdiv(self) -> int:
        return int(self.config.mesh.subdiv)

    @property
    def conditioned(self) -> bool:
        """True when the network takes the camera as an input (serves any camera)."""
        return bool(getattr(self.network.config, "view", False))

    @property
    def needs_geometry(self) -> bool:
        return hasattr(self.network, "geometry_mean")

    def recorded_camera(self, name: str) -> Camera | None:
        """The training camera `name` whole (`mvtex.data.camera.Camera`) as config.json
        records it, or None (not one of its cameras, or a model stored without the record)."""
        rig = self.config.rig
        return rig[name] if rig is not None and name in rig.names else None


def load_model(path: str | os.PathLike) -> LoadedModel:
    """Open a model directory written by `mvtex.tsnn.train.train`.

    Raises:
        InputError: naming config.json (and the key), model.safetensors or geometry.npz when
            one is missing, malformed, or does not match the others.
    """

    path = as_path(path, "path")
    if not path.is_dir():
        raise InputError(path, "model directory not found")
    config = ModelConfig.read(path)
    network = _network(config, path / CONFIG_FILE, path / "model.safetensors")
    geometry = None
    if config.geometry is not None:
        geometry = load_npz(path / GEOMETRY_FILE)
        if set(geometry) != {"rest_length", "groups"} or geometry["rest_length"].dtype.kind != "f" \
                or geometry["groups"].dtype.kind not in "iu":
            raise InputError(path / GEOMETRY_FILE, "needs arrays rest_length (float) and groups (integer), has "
                             + ", ".join(f"{k} {v.dtype}" for k, v in sorted(geometry.items())))
    return LoadedModel(path=path, config=config, network=network, geometry=geometry)


def _network(config: ModelConfig, file: Path, weights: Path):
    """The network of `config` with the weights of `weights`, in eval mode. It is built on
    the "meta" device (no memory) and compared with the file before anything is allocated:
    config.json cannot make us allocate more than the weights file holds."""
    import torch  # noqa: PLC0415 (loaded on use)

    try:
        with torch.device("meta"):
            network = build_network(config.architecture)
    except (TypeError, ValueError, OverflowError) as err:
        raise InputError(file, f"bad 'architecture' ({err})") from None
    state = read_weights(weights)
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
    network = build_network(config.architecture)
    network.load_state_dict({**network.state_dict(), **state})  # optional buffers absent: their defaults
    network.eval()
    return network


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
        (K,n',2) float32 d, times the model's gain (config.json's "gain", `TrainOptions.gain`).
    """
    d = _network_displacements(model, poses, uv, geometry=geometry, cam_from_world=cam_from_world,
                               batch_size=batch_size, device=device)
    if model.config.gain is not None and model.config.gain != 1.0:
        d *= np.float32(model.config.gain)
    return d


def _network_displacements(model: LoadedModel, poses: np.ndarray, uv: np.ndarray, *, geometry: np.ndarray | None,
                           cam_from_world: np.ndarray | None, batch_size: int, device: str) -> np.ndarray:
    """`predict_displacements` before the gain."""
    import torch  # noqa: PLC0415 (loaded on use)

    net = model.network.to(device)
    if getattr(net, "per_vertex", False):  # `gp`: d at the vertices, no atlas image
        if len(uv) != net.config.num_vertices:
            raise InputError(model.path / "config.json", f"predicts {net.config.num_vertices} vertices, "
                             f"the mesh has {len(uv)}")
        with torch.no_grad():
            return net(torch.from_numpy(np.array(poses, dtype=np.float64)).to(device)).cpu().numpy().astype(np.float32)
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
    import torch  # noqa: PLC0415 (loaded on use)

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


def check_serves(model: LoadedModel, dataset, subdiv: int) -> None:
    """Refuse (InputError naming the model's config.json and the dataset, in one line) a
    model that cannot serve this dataset: another base mesh (vertex count, faces or uv),
    another subdivision level than the other models, another pose dimension. Nothing else
    of the training dataset is asked: a model serves every set of its garment (its own
    dataset, an inference set of new frames, a corrected set), whatever its rest shape."""
    file = model.path / CONFIG_FILE
    mesh = model.config.mesh
    if model.subdiv != subdiv:
        raise InputError(file, f"subdivision level {model.subdiv} differs from the other models' ({subdiv}); "
                         "one texcoord set has one mesh: predict models of one level together")
    if mesh.num_base_vertices != dataset.num_vertices:
        raise InputError(file, f"made for a mesh of {mesh.num_base_vertices} vertices, {dataset.path} has "
                         f"{dataset.num_vertices}")
    if not mesh.made_for(dataset.faces, dataset.uv):
        raise InputError(file, f"made for another mesh than {dataset.path} (the same {dataset.num_vertices} "
                         "vertices, other faces or uv): import the frames with the training mesh's faces and uv")
    pose_dim = model.network.config.pose_dim
    if pose_dim != dataset.poses.shape[1]:
        raise InputError(file, f"expects {pose_dim}-dimensional poses, {dataset.path} has {dataset.poses.shape[1]}-"
                         "dimensional ones")


def _recorded_rig(jobs) -> tuple[Rig | None, list[Path]]:
    """The rig the models were trained for, camera by camera in the order predicted, from
    their config.json; with the models that do not record their cameras (older ones)."""
    cameras, unrecorded = [], []
    for name, m, _ in jobs:
        camera = m.recorded_camera(name)
        if camera is not None:
            cameras.append(camera)
        elif m.path not in unrecorded:
            unrecorded.append(m.path)
    return (Rig(tuple(cameras)) if not unrecorded else None), unrecorded


@writer("predict", inputs=lambda a: (a["dataset"], a["models"]))
def predict(dataset, models: Sequence[str | os.PathLike], out: str | os.PathLike, *, poses: Sequence[int],
            rig=None, progress: bool = True, device: str = "cpu", overwrite: bool = False) -> Path:
    """Run networks over poses and write a texcoord set.

    A model serves every dataset of its mesh and pose dimension (`check_serves`): its
    training dataset, or an inference set of new frames (DESIGN §4), for which it predicts
    exactly what it predicts for the same pose vectors and inferred meshes in its own.

    Args:
        dataset: the `mvtex.data.dataset.Dataset` (its mesh, inferred meshes and pose vectors;
            gt is not read).
        models: model directories (same subdivision level): one-camera models and/or a
            camera-conditioned one.
        out: texcoord set directory to write (atomically).
        poses: dataset pose indices, in the order of the set's rows.
        rig: a `mvtex.data.rig.Rig`: predict its cameras (a one-camera model serves its own
            camera, a camera-conditioned model every other camera of the rig). None: every
            model's own camera(s), and the set records the cameras the models were trained
            for (OUT/rig.yaml, from their config.json), so that triangulate, views, preview
            and eval need no rig; models stored without that record leave the set without
            one (said on stderr).
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

    dataset = as_dataset(dataset)
    out = as_path(out, "out")
    rig = None if rig is None else as_rig(rig)
    if isinstance(models, (str, os.PathLike)):
        models = [models]
    if not hasattr(models, "__iter__") or isinstance(models, (bytes, dict)):
        raise OptionError("models", f"must be a list of model folder paths, got {type(models).__name__}")
    models = [as_path(m, "models") for m in models]

    out = Path(out)
    if not models:
        raise InputError(out, "no model given")
    poses = dataset.check_poses(poses)
    loaded = [load_model(m) for m in models]
    first = loaded[0]
    for m in loaded:
        check_serves(m, dataset, first.subdiv)
    jobs = _jobs(loaded, rig)
    if rig is not None:
        unserved = [c for c in rig.names if c not in {name for name, _, _ in jobs}]
        if unserved:
            raise InputError(out, f"no model predicts camera(s) {', '.join(unserved)} of the rig: give a model "
                             "per camera or a camera-conditioned one")
    names = [name for name, _, _ in jobs]
    cameras, unrecorded = (rig.select(names), []) if rig is not None else _recorded_rig(jobs)
    faces, uv, parent = rebuild_mesh(dataset.faces, dataset.uv, first.subdiv)
    if len(uv) != first.config.mesh.num_vertices:
        raise InputError(first.path / CONFIG_FILE, f"mesh.num_vertices {first.config.mesh.num_vertices} but the "
                         f"mesh of {dataset.path} subdivided {first.subdiv} time(s) has {len(uv)}")
    references = {}
    for m in loaded:
        if m.geometry is not None:
            try:
                references[m.path] = MeshGeometry(dataset.faces, dataset.uv, arrays=m.geometry)
            except ValueError as err:
                raise InputError(m.path / GEOMETRY_FILE, f"does not fit {dataset.path}: {err}") from None
    x = np.asarray(dataset.poses[poses], dtype=np.float32).reshape(len(poses), -1)
    samplers: dict[tuple[int, int], AtlasSampler] = {}  # (resolution, dilation) -> the models' atlas
    # Block by block of poses, written into the files as they come: memory stays that of
    # one block (d of 10,000 poses and 24k vertices is 1.9 GB per camera).
    with atomic_path(out) as tmp, tqdm(total=len(poses) * len(jobs), desc="predict", unit="image",
                                       disable=not progress) as bar:
        tmp.mkdir()
        record = {"dataset": dataset_record(dataset), "models": {name: str(m.path) for name, m, _ in jobs}}
        if cameras is not None:
            record["rig"] = rig_record(cameras)
            save_rig(cameras, tmp / RIG_FILE)  # the set records its cameras: --rig defaults to them
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
            geometry: dict[tuple, np.ndarray] = {}
            for name, m, view in jobs:
                g = None
                if m.needs_geometry:
                    atlas = (m.network.config.resolution, int(m.config.dilation))
                    key = (*atlas, m.path if m.path in references else None)
                    if key not in geometry:
                        if atlas not in samplers:
                            samplers[atlas] = AtlasSampler(faces, uv, atlas[0], dilation=atlas[1], source=m.path)
                        geometry[key] = geometry_images(dataset, rows, samplers[atlas], parent,
                                                        geometry=references.get(m.path))
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
    if unrecorded:  # said once the set is written (an error would make it a second line)
        print(f"mvtex predict: warning: {unrecorded[0] / CONFIG_FILE} records no cameras (a model trained before "
              f"models recorded them): {out} records no rig; give --rig to predict, or to the commands that read "
              "the set", file=sys.stderr)
    return out
