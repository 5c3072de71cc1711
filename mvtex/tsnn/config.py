"""config.json of a model directory: the one schema `train` writes and `load_model` reads.

    {"format": "mvtex-tsnn", "version": 3,
     "camera": name | null (null: one network conditioned on the camera),
     "inputs": the content fingerprint of what it was trained from,
     "cameras": {name: 3x4 cam_from_world | null} of the training cameras,
     "rig": {name: {"width", "height", "K", "dist", "R", "t"}} the training cameras whole
            (what `predict` records as the set's rig.yaml); absent in older models,
     "architecture": {"arch": "gp"|"mlp"|"unet"|"paper", ...},
     "pose_normalisation", "output_scale",
     "gain": the factor every prediction is multiplied by, in [0, 1], fitted on the
             validation poses (`TrainOptions.gain`); absent: 1,
     "mesh": {"subdiv", "num_base_vertices", "num_vertices", "num_faces",
              "base_mesh": fingerprint of the base mesh's faces and uv},
     "atlas": {"convention", "dilation"},
     "geometry": {"file": "geometry.npz"} (unet: the reference its geometry images are
                 measured against, so that it serves any set of its garment),
     "dataset", "texcoords", "split", "options", "device", "torch_version",
     "epochs_run", "best_epoch", "seconds", "losses", "history"}

Versions 1 and 2 are read too (version 1: the paper's architecture without an "arch" key;
version 2: the base mesh named by its SHA-256, "base_mesh_sha256"). Only the keys a
prediction needs are required; the training record is optional (a hand-written model has
none). Every problem is an InputError naming config.json and the key.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from mvtex.data.camera import MAX_COORDINATE_M, Camera, check_camera_name
from mvtex.data.limits import MAX_SUBDIV
from mvtex.data.rig import Rig
from mvtex.tsnn.options import MAX_RESOLUTION, MAX_WIDTH
from mvtex.util.checks import as_path
from mvtex.util.errors import InputError
from mvtex.util.files import read_json
from mvtex.util.fingerprint import fingerprint

MODEL_FORMAT = "mvtex-tsnn"


MODEL_VERSION = 3
# version 1: paper architecture, one camera, no "arch" key; version 2: the base mesh named
# by its SHA-256 ("base_mesh_sha256"), version 3 by `mvtex.util.fingerprint` ("base_mesh")
READABLE_VERSIONS = (1, 2, 3)


CONFIG_FILE = "config.json"


GEOMETRY_FILE = "geometry.npz"


def mesh_fingerprint(faces: np.ndarray, uv: np.ndarray) -> str:
    """The fingerprint of a base mesh's faces (int32) and uv (float32): ties a model to its mesh."""

    return fingerprint(np.asarray(faces, dtype=np.int32), np.asarray(uv, dtype=np.float32))


@dataclass(frozen=True)
class MeshRecord:
    """config.json's "mesh": the base mesh a model was made for and its subdivision.

    Attributes:
        subdiv: midpoint subdivision levels of the texcoord mesh the model predicts.
        num_base_vertices: n of the base mesh; num_vertices: n' after subdivision.
        base_mesh: `mesh_fingerprint` of the base faces and uv (version 3), or None.
        base_mesh_sha256: the SHA-256 of the base faces and uv (versions 1-2), or None.
        num_faces: faces after subdivision (None where not recorded).
    """

    subdiv: int
    num_base_vertices: int
    num_vertices: int
    base_mesh: str | None = None
    base_mesh_sha256: str | None = None
    num_faces: int | None = None

    def made_for(self, faces: np.ndarray, uv: np.ndarray) -> bool:
        """Whether this record names the base mesh of these faces and uv."""
        if self.base_mesh is not None:
            return self.base_mesh == mesh_fingerprint(faces, uv)
        h = hashlib.sha256()  # models written before version 3
        h.update(np.ascontiguousarray(faces, dtype=np.int32).tobytes())
        h.update(np.ascontiguousarray(uv, dtype=np.float32).tobytes())
        return self.base_mesh_sha256 == h.hexdigest()

    def to_json(self) -> dict:
        out: dict[str, Any] = {"subdiv": self.subdiv, "num_base_vertices": self.num_base_vertices,
                               "num_vertices": self.num_vertices}
        if self.num_faces is not None:
            out["num_faces"] = self.num_faces
        if self.base_mesh is not None:
            out["base_mesh"] = self.base_mesh
        if self.base_mesh_sha256 is not None:
            out["base_mesh_sha256"] = self.base_mesh_sha256
        return out


def camera_record(camera: Camera) -> dict:
    """What config.json's "rig" holds of a camera: width, height, K, dist, R, t."""
    return {"width": camera.width, "height": camera.height, "K": camera.K.tolist(), "dist": camera.dist.tolist(),
            "R": camera.R.tolist(), "t": camera.t.tolist()}


# The training record: optional keys, written in this order after the model's own ones.
_RECORD = ("pose_normalisation", "output_scale", "dataset", "texcoords", "split", "options", "device",
           "torch_version", "epochs_run", "best_epoch", "seconds", "losses", "history")


@dataclass(frozen=True)
class ModelConfig:
    """A model directory's config.json (the module docstring lists its keys).

    Attributes:
        camera: the camera of a one-camera model; None for a camera-conditioned network.
        architecture: the network's architecture (`mvtex.tsnn.model.build_network`).
        mesh: the base mesh the model was made for (`MeshRecord`).
        version: the format version it was written with.
        cameras: the training cameras, name -> (3,4) cam_from_world (None for a one-camera
            model's implicit camera), or None where not recorded.
        rig: the training cameras whole (a `Rig`), or None in models written before they
            were recorded.
        atlas: {"convention", "dilation"} of atlas-image models, or None.
        geometry: {"file": GEOMETRY_FILE} where a `unet` keeps its geometry reference.
        inputs: the content fingerprint of everything it was trained from, or None.
        gain: the factor in [0, 1] every prediction is multiplied by (fitted on the
            validation poses, `TrainOptions.gain`); None: 1.
        pose_normalisation ... history: the training record (None where absent).
    """

    camera: str | None
    architecture: dict[str, Any]
    mesh: MeshRecord
    version: int = MODEL_VERSION
    cameras: dict[str, np.ndarray | None] | None = None
    rig: Rig | None = None
    atlas: dict[str, Any] | None = None
    geometry: dict[str, Any] | None = None
    inputs: str | None = None
    gain: float | None = None
    pose_normalisation: dict[str, Any] | None = None
    output_scale: float | None = None
    dataset: dict[str, Any] | None = None
    texcoords: dict[str, Any] | None = None
    split: dict[str, list[int]] | None = None
    options: dict[str, Any] | None = None
    device: str | None = None
    torch_version: str | None = None
    epochs_run: int | None = None
    best_epoch: int | None = None
    seconds: float | None = None
    losses: dict[str, Any] | None = None
    history: dict[str, list[float]] | None = None

    @property
    def conditioned(self) -> bool:
        """True when the network takes the camera as an input (serves any camera)."""
        return bool(self.architecture.get("view", False))

    @property
    def dilation(self) -> int | None:
        return None if self.atlas is None else self.atlas.get("dilation")

    def to_json(self) -> dict:
        """config.json's object, keys in the documented order, absent ones left out."""
        out: dict[str, Any] = {"format": MODEL_FORMAT, "version": self.version, "camera": self.camera}
        if self.inputs is not None:
            out["inputs"] = self.inputs
        if self.cameras is not None:
            out["cameras"] = {k: None if v is None else np.asarray(v).tolist() for k, v in self.cameras.items()}
        if self.rig is not None:
            out["rig"] = {cam.name: camera_record(cam) for cam in self.rig}
        out["architecture"] = self.architecture
        for key in _RECORD[:2]:
            if getattr(self, key) is not None:
                out[key] = getattr(self, key)
        if self.gain is not None:
            out["gain"] = self.gain
        out["mesh"] = self.mesh.to_json()
        for key in ("atlas", "geometry", *_RECORD[2:]):
            if getattr(self, key) is not None:
                out[key] = getattr(self, key)
        return out

    def write(self, directory: str | os.PathLike) -> Path:
        """Write config.json into an existing directory (the caller makes it atomic)."""
        path = Path(directory) / CONFIG_FILE
        path.write_text(json.dumps(self.to_json(), indent=2) + "\n")
        return path

    @classmethod
    def read(cls, directory: str | os.PathLike) -> "ModelConfig":
        """Read and check DIRECTORY/config.json.

        Raises:
            InputError: naming config.json and the key that is missing or malformed.
        """
        file = as_path(directory, "directory") / CONFIG_FILE
        return cls.from_json(read_json(file), file)

    @classmethod
    def from_json(cls, meta: Any, file: str | os.PathLike) -> "ModelConfig":
        """The config of a parsed config.json object; InputError naming `file` and the key."""
        if not isinstance(meta, dict) or meta.get("format") != MODEL_FORMAT:
            raise InputError(file, f'not a TSNN model (format must be "{MODEL_FORMAT}")')
        version = meta.get("version")
        if isinstance(version, bool) or version not in READABLE_VERSIONS:
            raise InputError(file, f"unsupported version {version!r} "
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
        _check_sizes(arch, file)
        config = cls(camera=camera, architecture=arch, mesh=_mesh(meta, file), version=version,
                     cameras=_cameras(meta.get("cameras"), file), rig=_rig(meta.get("rig"), file),
                     atlas=_optional(meta, file, "atlas", dict), geometry=_optional(meta, file, "geometry", dict),
                     inputs=_optional(meta, file, "inputs", str), gain=_gain(meta, file),
                     **{key: _optional(meta, file, key, _KINDS[key]) for key in _RECORD})
        _check_consistent(config, file)
        return config


def _gain(meta: dict, file) -> float | None:
    gain = _optional(meta, file, "gain", (int, float))
    if gain is not None and not 0.0 <= gain <= 1.0:  # NaN fails both
        raise InputError(file, f"'gain' must be a number in [0, 1], got {gain}")
    return None if gain is None else float(gain)


def _check_consistent(config: ModelConfig, file) -> None:
    """What one key of config.json says about another: the camera and the architecture's
    view, the training cameras, a unet's atlas, the geometry file, the recorded rig."""
    camera = config.camera
    if config.conditioned == (camera is not None):
        raise InputError(file, "'camera' must be null exactly when the architecture is conditioned on the view")
    if config.conditioned and (not config.cameras or any(v is None for v in config.cameras.values())):
        raise InputError(file, "'cameras' must map camera names to finite 3x4 cam_from_world matrices")
    if config.architecture.get("arch") == "unet":
        dilation = config.dilation
        if not isinstance(dilation, int) or isinstance(dilation, bool) or not 0 <= dilation <= 64:
            raise InputError(file, "missing or malformed 'atlas.dilation'")
    if config.geometry is not None and config.geometry.get("file") != GEOMETRY_FILE:
        raise InputError(file, f"malformed 'geometry' (expected {{\"file\": \"{GEOMETRY_FILE}\"}})")
    if config.rig is not None:
        trained = [camera] if camera is not None else list(config.cameras)
        if sorted(config.rig.names) != sorted(trained):
            raise InputError(file, f"'rig' holds cameras {', '.join(config.rig.names)}, the model was trained "
                             f"for {', '.join(trained)}")


_KINDS: dict[str, type | tuple[type, ...]] = {
    "pose_normalisation": dict, "output_scale": (int, float), "dataset": dict, "texcoords": dict, "split": dict,
    "options": dict, "device": str, "torch_version": str, "epochs_run": int, "best_epoch": int,
    "seconds": (int, float), "losses": dict, "history": dict}


def _require(meta: dict, file, key: str, kind: type | tuple[type, ...]):
    value = meta.get(key)
    if not isinstance(value, kind) or isinstance(value, bool):
        raise InputError(file, f"missing or malformed '{key}'")
    return value


def _optional(meta: dict, file, key: str, kind: type | tuple[type, ...]):
    value = meta.get(key)
    if value is None:
        return None
    if not isinstance(value, kind) or isinstance(value, bool):
        raise InputError(file, f"malformed '{key}'")
    return value


def _check_sizes(arch: dict, file) -> None:
    """Sizes are checked before the network is built: config.json cannot make us allocate
    more than the weights file holds."""
    widths = arch.get("widths") if isinstance(arch.get("widths"), (list, tuple)) else ()
    sizes = [arch.get("resolution"), arch.get("width"), arch.get("min_width"), *widths]
    if any(isinstance(v, (int, float)) and not isinstance(v, bool) and v > limit
           for v, limit in zip(sizes, [MAX_RESOLUTION] + [MAX_WIDTH] * (len(sizes) - 1))):
        raise InputError(file, f"architecture too large (resolution at most {MAX_RESOLUTION}, "
                         f"channels at most {MAX_WIDTH})")


def _mesh(meta: dict, file) -> MeshRecord:
    mesh = _require(meta, file, "mesh", dict)
    for key in ("subdiv", "num_base_vertices", "num_vertices"):
        if not isinstance(mesh.get(key), int) or isinstance(mesh.get(key), bool) or mesh[key] < 0:
            raise InputError(file, f"missing or malformed 'mesh.{key}'")
    base, legacy = mesh.get("base_mesh"), mesh.get("base_mesh_sha256")
    if not isinstance(base if base is not None else legacy, str):
        raise InputError(file, "missing or malformed 'mesh.base_mesh'")
    if mesh["subdiv"] > MAX_SUBDIV:
        raise InputError(file, f"mesh.subdiv is {mesh['subdiv']}, at most {MAX_SUBDIV} is supported")
    faces = mesh.get("num_faces")
    if faces is not None and (not isinstance(faces, int) or isinstance(faces, bool) or faces < 0):
        raise InputError(file, "malformed 'mesh.num_faces'")
    return MeshRecord(subdiv=mesh["subdiv"], num_base_vertices=mesh["num_base_vertices"],
                      num_vertices=mesh["num_vertices"], base_mesh=base if isinstance(base, str) else None,
                      base_mesh_sha256=legacy if base is None else None, num_faces=faces)


def _cameras(raw: Any, file) -> dict[str, np.ndarray | None] | None:
    """"cameras": name -> a finite 3x4 matrix, or null (a one-camera model's own camera)."""
    if raw is None:
        return None
    if not isinstance(raw, dict) or not raw:
        raise InputError(file, "malformed 'cameras' (camera names -> 3x4 cam_from_world matrices)")
    out: dict[str, np.ndarray | None] = {}
    for name, value in raw.items():
        if value is None:
            out[str(name)] = None
            continue
        try:
            matrix = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            matrix = np.zeros(0)
        if matrix.shape != (3, 4) or not np.all(np.isfinite(matrix)) or np.abs(matrix).max() > MAX_COORDINATE_M:
            raise InputError(file, "'cameras' must map camera names to finite 3x4 cam_from_world matrices with "
                             f"entries at most {MAX_COORDINATE_M:g} in magnitude ('cameras.{name}' is not one)")
        out[str(name)] = matrix
    return out


def _rig(raw: Any, file) -> Rig | None:
    """"rig": name -> camera record, as a `Rig`; each camera checked as a rig file's are."""
    if raw is None:
        return None
    if not isinstance(raw, dict) or not raw:
        raise InputError(file, "malformed 'rig' (camera names -> width, height, K, dist, R, t)")
    cameras = []
    for name, rec in raw.items():
        if not isinstance(rec, dict):
            raise InputError(file, f"malformed 'rig.{name}' (width, height, K, dist, R, t)")
        try:
            cameras.append(Camera(name=str(name), width=rec["width"], height=rec["height"], K=rec["K"], R=rec["R"],
                                  t=rec["t"], dist=rec.get("dist", np.zeros(5))))
        except KeyError as err:
            raise InputError(file, f"missing 'rig.{name}.{err.args[0]}'") from None
        except (ValueError, TypeError) as err:
            raise InputError(file, f"malformed 'rig.{name}' ({getattr(err, 'problem', err)})") from None
    try:
        return Rig(tuple(cameras))
    except ValueError as err:
        raise InputError(file, f"malformed 'rig' ({getattr(err, 'problem', err)})") from None


def training_rig(rig: Rig | None, texcoords, cameras: list[str]) -> Rig | None:
    """The cameras a model is trained for, whole, to record in its config.json: from `rig`
    where it holds them all, else from the texcoord set's record of its cameras
    (texcoords.json "rig", which `slide`, `views` and `predict` with a rig write); None
    when neither has them all."""
    if rig is not None and all(c in rig.names for c in cameras):
        return rig.select(list(cameras))
    recorded = texcoords.meta.get("rig")
    if not isinstance(recorded, Mapping) or not all(isinstance(recorded.get(c), Mapping) for c in cameras):
        return None
    try:
        return Rig(tuple(Camera(name=c, width=recorded[c]["width"], height=recorded[c]["height"],
                                K=recorded[c]["K"], R=recorded[c]["R"], t=recorded[c]["t"],
                                dist=recorded[c].get("dist", np.zeros(5))) for c in cameras))
    except (KeyError, TypeError, ValueError):
        return None
