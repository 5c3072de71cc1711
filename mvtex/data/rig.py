"""Camera rigs: an ordered set of uniquely named `Camera`s, stored as OpenCV FileStorage YAML
(`format: "mvtex-rig"`, `version: 1`, a sequence `cameras` of maps with `name`, `width`,
`height`, `K` 3x3, `dist` 1x5, `R` 3x3, `t` 3x1), read and written with `cv2.FileStorage`;
the rigs shipped with mvtex (`stereo`, `square4`, `trapezoid12`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from mvtex.data.camera import MAX_IMAGE_SIZE, Camera, undistorted_camera
from mvtex.util.checks import as_list
from mvtex.util.errors import InputError, OptionError
from mvtex.util.files import read_row
from mvtex.util.output import atomic_path, claim_file
from mvtex.util.resources import resource_path

RIG_FORMAT = "mvtex-rig"


RIG_VERSION = 1


@dataclass(frozen=True)
class Rig:
    """An ordered set of at least one uniquely named camera (`Camera`).

    Attributes:
        cameras: the cameras, in order.
        source: the rig file it was read from (`load_rig`), which errors about the rig
            name; None for a rig made in code. Not part of equality.

    Raises:
        OptionError: `cameras` is not a sequence of `Camera`s, is empty, or names a camera
            twice (ignoring case).
    """

    cameras: tuple[Camera, ...]
    source: Path | None = field(default=None, compare=False)

    def __post_init__(self) -> None:

        object.__setattr__(self, "cameras", tuple(as_list(self.cameras, "cameras", what="Camera")))
        if self.source is not None:
            if not isinstance(self.source, (str, os.PathLike)):
                raise OptionError("source", f"must be a file path or None, got {type(self.source).__name__}")
            object.__setattr__(self, "source", Path(self.source))
        wrong = [type(c).__name__ for c in self.cameras if not isinstance(c, Camera)]
        if wrong:
            raise OptionError("cameras", f"must be a sequence of Camera, got an element of type {wrong[0]}")
        if not self.cameras:
            raise OptionError("cameras", "must hold at least one camera, got none")
        names = [c.name for c in self.cameras]
        # Unique without case too: the names become folders on case-insensitive file systems.
        if len({n.lower() for n in names}) != len(names):
            raise OptionError("camera", f"names must be unique (ignoring case), got {names}")

    def __iter__(self) -> Iterator[Camera]:
        return iter(self.cameras)

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def __getitem__(self, name: str) -> Camera:
        """The camera of this name; `UnknownCamera` (an OptionError and a KeyError) if none."""
        for cam in self.cameras:
            if cam.name == name:
                return cam
        raise UnknownCamera(name, self.names)

    def select(self, names: Sequence[str] | None) -> "Rig":
        """The sub-rig with these camera names (all if None or empty), from the same source;
        unknown names raise InputError naming the rig's file."""

        if names is None:
            return self
        names = as_list(names, "cameras", str, "camera names")
        if not names:
            return self
        unknown = [n for n in names if n not in self.names]
        if unknown:
            raise InputError(self.source, f"no camera named {', '.join(unknown)} (the rig has "
                             f"{', '.join(self.names)})")
        return Rig(tuple(self[n] for n in names), self.source)


class UnknownCamera(OptionError, KeyError):
    """`Rig[name]` of a name the rig does not have: an OptionError (exit code 2 from the CLI)
    that `except KeyError` also catches."""

    def __init__(self, name, names: Sequence[str] = ()):
        self.name = name
        self.names = list(names)
        OptionError.__init__(self, None, f"camera: no camera named {name!r} (the rig has {', '.join(self.names)})")

    def __str__(self) -> str:  # KeyError would quote the message
        return self.args[0]

    def __reduce__(self):
        return type(self), (self.name, self.names)


def save_rig(rig: Rig, path: str | os.PathLike, *, overwrite: bool = False) -> None:
    """Write a rig as OpenCV FileStorage YAML (atomically), under the writer policy of
    `mvtex.util.output.claim_file`: an existing file is replaced only with `overwrite`.

    The file is read back with `load_rig`'s reader before it is renamed into place and must
    give the same cameras: `save_rig` writes exactly the rigs `load_rig` accepts.

    Raises:
        OptionError: `rig` is not a `Rig`, or a camera would not read back as it is.
    """
    import cv2  # noqa: PLC0415 (loaded on use)

    if not isinstance(rig, Rig):
        raise OptionError("rig", f"must be a Rig, got {type(rig).__name__}")
    if not isinstance(path, (str, os.PathLike)):
        raise OptionError("path", f"must be a file path, got {type(path).__name__}")
    path = Path(path)
    with claim_file(path, "save_rig", overwrite=overwrite), atomic_path(path) as tmp:
        # FileStorage writes into memory (its file writer fails silently on a full disk) and
        # Python writes the file: a failed write is an OSError the claim names the output by.
        tmp_yaml = tmp.with_name(tmp.name + ".yaml")
        fs = cv2.FileStorage(".yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
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
        tmp_yaml.write_text(fs.releaseAndGetString())
        _check_reads_back(rig, tmp_yaml)
        os.replace(tmp_yaml, tmp)


def _check_reads_back(rig: Rig, written: Path) -> None:
    """Refuse (OptionError) a written rig file that `load_rig` refuses or reads differently."""
    try:
        loaded = load_rig(written)
    except InputError as err:
        written.unlink(missing_ok=True)
        raise OptionError("rig", f"would be written as a file the rig reader refuses ({err.problem})") from None
    for cam, back in zip(rig, loaded):
        same = (cam.name == back.name and (cam.width, cam.height) == (back.width, back.height)
                and all(np.array_equal(getattr(cam, k), getattr(back, k)) for k in ("K", "R", "t", "dist")))
        if not same:
            written.unlink(missing_ok=True)
            raise OptionError("rig", f"camera {cam.name!r} does not read back as written")


def load_rig(path: str | os.PathLike) -> Rig:
    """Read an mvtex-rig YAML, or a built-in rig by name (`stereo`, `square4`,
    `trapezoid12`); any problem raises InputError naming the file. Every camera is checked
    by `Camera` (the same checks `save_rig` makes)."""
    import cv2  # noqa: PLC0415 (loaded on use)

    if not isinstance(path, (str, os.PathLike)):
        raise OptionError("rig", f"must be a rig file path or a built-in rig name, got {type(path).__name__}")
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
            return Rig(tuple(cameras), path)
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
    R = matrix("R", 9).reshape(3, 3)  # a rotation: `Camera` checks it, as for every camera
    if not name:
        raise InputError(path, f"camera {index}: empty name")
    fields = dict(width=integer("width"), height=integer("height"), K=matrix("K", 9).reshape(3, 3),
                  dist=matrix("dist", 5) if not node.getNode("dist").empty() else np.zeros(5), R=R, t=matrix("t", 3))
    try:  # the fields' own errors above name the file once; Camera's checks name no file
        return Camera(name=name, **fields)
    except ValueError as err:
        raise InputError(path, f"camera {index}: {err}" if not str(err).startswith("camera ") else str(err)) from None


def check_sees(rig: Rig, positions: np.ndarray, *, what: str = "the mesh") -> None:
    """Refuse (InputError naming the rig's file) a camera that sees none of the points
    (..., 3): behind it or outside its image (a rig for another scene, wrong R, t or K)."""
    blind = [cam.name for cam in rig if not cam.sees(positions)]
    if blind:
        raise InputError(rig.source, f"camera {blind[0]!r} sees nothing of {what}: check its R, t and K")


def winding_numbers(points: np.ndarray, positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Generalised winding numbers of points (N,3) with respect to a triangle mesh: the
    summed signed solid angle of its triangles over 4π (Van Oosterom & Strackee's formula),
    ±1 inside a closed mesh, 0 outside, fractional near the holes of an open one.

    Returns:
        (N,) float64.
    """
    tri = np.asarray(positions, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]  # (m,3,3)
    out = np.zeros(len(points))
    for i, p in enumerate(np.asarray(points, dtype=np.float64)):
        a, b, c = (tri[:, k] - p for k in range(3))
        la, lb, lc = (np.linalg.norm(v, axis=1) for v in (a, b, c))
        det = np.einsum("ij,ij->i", a, np.cross(b, c))
        den = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la \
            + np.einsum("ij,ij->i", c, a) * lb
        out[i] = np.sum(2.0 * np.arctan2(det, den)) / (4.0 * np.pi)
    return out


def check_outside_body(rig: Rig, dataset, poses: Sequence[int]) -> None:
    """Refuse (InputError naming the rig's file) a camera whose centre lies
    inside the dataset's body at one of `poses`: it would see the body's inside only.

    Inside means a winding number above 1/2 (`winding_numbers`; exact for a closed body,
    robust to small holes); it is computed only where the centre is inside the body's
    bounding box at that pose. Without a body nothing is checked.
    """

    body = getattr(dataset, "body", None)
    if body is None:
        return
    centers = np.stack([cam.center for cam in rig])
    for k in poses:
        positions = read_row(body.positions, int(k)).astype(np.float64)
        low, high = positions.min(axis=0), positions.max(axis=0)
        boxed = np.flatnonzero(np.all((centers >= low) & (centers <= high), axis=1))
        if not len(boxed):
            continue
        inside = np.abs(winding_numbers(centers[boxed], positions, body.faces)) > 0.5
        if inside.any():
            cam = rig.cameras[int(boxed[np.argmax(inside)])]
            raise InputError(rig.source, f"camera {cam.name!r} is inside the body of {dataset.path} at pose {int(k)} "
                             f"(its centre {np.round(cam.center, 4).tolist()} lies within the body mesh): "
                             "check its R and t")


def as_rig(rig: "Rig | str | os.PathLike") -> Rig:
    """A `Rig` as is, or a rig path / built-in rig name loaded (`load_rig`, which records
    the file as the rig's `source`)."""
    if isinstance(rig, Rig):
        return rig
    if not isinstance(rig, (str, os.PathLike)):
        raise OptionError("rig", f"must be a Rig, a rig file path or a built-in rig name, got {type(rig).__name__}")
    return load_rig(rig)


def builtin_rig_file(name: str) -> Path:
    """Path of a rig shipped with mvtex (`stereo`, `square4`, `trapezoid12`)."""

    return resource_path("calib", f"{name}.yaml")


def resolve_rig(spec: str | os.PathLike) -> Path:
    """A rig argument: a YAML path, or the name of a built-in rig."""
    path = Path(spec)
    if path.exists() or path.suffix in (".yaml", ".yml"):
        return path
    builtin = builtin_rig_file(str(spec))
    return builtin if builtin.is_file() else path


def undistort_rig(rig: Rig, alpha: float | None = None) -> Rig:
    """Every camera of a rig made pinhole (see `undistorted_camera`)."""
    return Rig(tuple(undistorted_camera(cam, alpha) for cam in rig))
