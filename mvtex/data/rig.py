"""Camera rigs: an ordered set of uniquely named `Camera`s, stored as OpenCV FileStorage YAML
(`format: "mvtex-rig"`, `version: 1`, a sequence `cameras` of maps with `name`, `width`,
`height`, `K` 3x3, `dist` 1x5, `R` 3x3, `t` 3x1), read and written with `cv2.FileStorage`;
the rigs shipped with mvtex (`stereo`, `square4`, `trapezoid12`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from mvtex.data.camera import MAX_IMAGE_SIZE, Camera, undistorted_camera
from mvtex.util.errors import InputError

RIG_FORMAT = "mvtex-rig"


RIG_VERSION = 1


@dataclass(frozen=True)
class Rig:
    """An ordered set of uniquely named cameras."""

    cameras: tuple[Camera, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "cameras", tuple(self.cameras))
        names = [c.name for c in self.cameras]
        # Unique without case too: the names become folders on case-insensitive file systems.
        if len({n.lower() for n in names}) != len(names):
            raise ValueError(f"camera names must be unique (ignoring case), got {names}")

    def __iter__(self) -> Iterator[Camera]:
        return iter(self.cameras)

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def __getitem__(self, name: str) -> Camera:
        for cam in self.cameras:
            if cam.name == name:
                return cam
        raise KeyError(name)

    def select(self, names: Sequence[str] | None, source: str | os.PathLike | None = None) -> "Rig":
        """The sub-rig with these camera names (all if None); unknown names raise InputError."""
        if not names:
            return self
        unknown = [n for n in names if n not in self.names]
        if unknown:
            raise InputError(source, f"no camera named {', '.join(unknown)} (the rig has {', '.join(self.names)})")
        return Rig(tuple(self[n] for n in names))


def save_rig(rig: Rig, path: str | os.PathLike, *, overwrite: bool = False) -> None:
    """Write a rig as OpenCV FileStorage YAML (atomically), under the writer policy of
    `mvtex.util.output.claim_file`: an existing file is replaced only with `overwrite`."""
    import cv2

    from mvtex.util.output import atomic_path, claim_file

    path = Path(path)
    with claim_file(path, "save_rig", overwrite=overwrite), atomic_path(path) as tmp:
        # FileStorage picks the format from the extension: keep ".yaml" on the temporary.
        tmp_yaml = tmp.with_name(tmp.name + ".yaml")
        fs = cv2.FileStorage(str(tmp_yaml), cv2.FILE_STORAGE_WRITE)
        fs.write("format", RIG_FORMAT)
        fs.write("version", RIG_VERSION)
        fs.startWriteStruct("cameras", cv2.FileNode_SEQ)
        for cam in rig:
            fs.startWriteStruct("", cv2.FileNode_MAP)
            fs.write("name", cam.name)
            fs.write("width", cam.width)
            fs.write("height", cam.height)
            fs.write("K", cam.K)
            fs.write("dist", cam.dist.reshape(1, 5))
            fs.write("R", cam.R)
            fs.write("t", cam.t.reshape(3, 1))
            fs.endWriteStruct()
        fs.endWriteStruct()
        fs.release()
        os.replace(tmp_yaml, tmp)


def load_rig(path: str | os.PathLike) -> Rig:
    """Read an mvtex-rig YAML, or a built-in rig by name (`stereo`, `square4`,
    `trapezoid12`); any problem raises InputError naming the file."""
    import cv2

    path = resolve_rig(path)
    if not path.is_file():
        raise InputError(path, "rig file not found")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_FORMAT_YAML)
    except (cv2.error, SystemError) as err:  # OpenCV 5 surfaces parse errors as either
        raise InputError(path, f"malformed rig YAML ({_opencv_detail(getattr(err, '__cause__', None) or err)})") from None
    try:
        if not fs.isOpened():
            raise InputError(path, "cannot be read as OpenCV YAML")
        fmt = fs.getNode("format")
        if fmt.empty() or fmt.string() != RIG_FORMAT:
            raise InputError(path, f'not an mvtex rig (missing format: "{RIG_FORMAT}")')
        version = fs.getNode("version")
        if version.empty() or int(version.real()) != RIG_VERSION:
            raise InputError(path, f"unsupported rig version (expected {RIG_VERSION})")
        seq = fs.getNode("cameras")
        if seq.empty() or not seq.isSeq() or seq.size() == 0:
            raise InputError(path, "no 'cameras' sequence")
        cameras = []
        for i in range(seq.size()):
            try:  # a damaged document can hold a scalar where a map should be; OpenCV asserts
                cameras.append(_camera_from_node(seq.at(i), path, i))
            except cv2.error as err:
                raise InputError(path, f"camera {i}: malformed entry ({_opencv_detail(err)})") from None
        try:
            return Rig(tuple(cameras))
        except ValueError as err:
            raise InputError(path, str(err)) from None
    finally:
        fs.release()


def _opencv_detail(err: BaseException) -> str:
    """The last line of an OpenCV error: the assertion or parse message, without its banner."""
    lines = str(err).strip().splitlines()
    return lines[-1] if lines else "parse error"


def _camera_from_node(node, path: Path, index: int) -> Camera:
    def need(key: str):
        child = node.getNode(key)
        if child.empty():
            raise InputError(path, f"camera {index}: missing '{key}'")
        return child

    def matrix(key: str, size: int) -> np.ndarray:
        child = need(key)
        m = child.mat() if child.isMap() else None
        if m is None:
            raise InputError(path, f"camera {index}: '{key}' is not an OpenCV matrix")
        m = np.asarray(m, dtype=np.float64).reshape(-1)
        if not np.all(np.isfinite(m)):
            raise InputError(path, f"camera {index}: '{key}' has NaN or infinite values")
        if m.size != size:
            raise InputError(path, f"camera {index}: '{key}' has {m.size} values, expected {size}")
        return m

    def integer(key: str) -> int:
        child = need(key)
        if not (child.isInt() or child.isReal()):
            raise InputError(path, f"camera {index}: '{key}' must be an integer, got {child.string()!r}")
        value = child.real()
        if not float(value).is_integer() or not 1 <= value <= MAX_IMAGE_SIZE:
            raise InputError(path, f"camera {index}: '{key}' must be an integer in 1..{MAX_IMAGE_SIZE}, got {value}")
        return int(value)

    name_node = need("name")
    if not name_node.isString():
        raise InputError(path, f"camera {index}: 'name' must be a string")
    name = name_node.string()
    R = matrix("R", 9).reshape(3, 3)
    if not np.all(np.isfinite(R)) or np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
        raise InputError(path, f"camera {index}: R is not a rotation matrix")
    if not name:
        raise InputError(path, f"camera {index}: empty name")
    fields = dict(width=integer("width"), height=integer("height"), K=matrix("K", 9).reshape(3, 3),
                  dist=matrix("dist", 5) if not node.getNode("dist").empty() else np.zeros(5), R=R, t=matrix("t", 3))
    try:  # the fields' own errors above name the file once; Camera's checks are plain ValueErrors
        return Camera(name=name, **fields)
    except ValueError as err:
        raise InputError(path, str(err)) from None


def check_sees(rig: Rig, positions: np.ndarray, source: str | os.PathLike | None = None, *,
               what: str = "the mesh") -> None:
    """Refuse (InputError naming `source`, e.g. the rig file) a camera that sees none of the
    points (..., 3): behind it or outside its image (a rig for another scene, wrong R, t or K)."""
    blind = [cam.name for cam in rig if not cam.sees(positions)]
    if blind:
        raise InputError(source, f"camera {blind[0]!r} sees nothing of {what}: check its R, t and K")


def as_rig(rig: "Rig | str | os.PathLike") -> tuple[Rig, Path | None]:
    """A `Rig` as is (source None), or a rig path / built-in rig name loaded: (rig, its file)."""
    if isinstance(rig, Rig):
        return rig, None
    path = resolve_rig(rig)
    return load_rig(path), path


def builtin_rig_path(name: str) -> Path:
    """Path of a rig shipped with mvtex (`stereo`, `square4`, `trapezoid12`)."""
    from mvtex.util.resources import resource_path

    return resource_path("calib", f"{name}.yaml")


def resolve_rig(spec: str | os.PathLike) -> Path:
    """A rig argument: a YAML path, or the name of a built-in rig."""
    path = Path(spec)
    if path.exists() or path.suffix in (".yaml", ".yml"):
        return path
    builtin = builtin_rig_path(str(spec))
    return builtin if builtin.is_file() else path


def undistort_rig(rig: Rig, alpha: float | None = None) -> Rig:
    """Every camera of a rig made pinhole (see `undistorted_camera`)."""
    return Rig(tuple(undistorted_camera(cam, alpha) for cam in rig))
