"""Rig operations behind `mvtex rig` and `mvtex undistort`: summaries, pictures, COLMAP
import/export and undistortion, each refusing to replace files mvtex did not write.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from mvtex.calibration.images import read_image
from mvtex.calibration.output import plot_rig
from mvtex.data.camera import undistort_image, undistorted_camera
from mvtex.data.rig import Rig, save_rig, undistort_rig
from mvtex.formats.colmap import read_rig, write_rig
from mvtex.util.errors import InputError, OptionError
from mvtex.util.files import save_png, write_json
from mvtex.util.output import atomic_path, writer

UNDISTORT_FORMAT = "mvtex-undistorted"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def rig_summary(rig: Rig) -> dict:
    """Per camera its size, intrinsics, whether it has distortion, its centre; and the
    baselines between camera centres (meters)."""
    cameras = {}
    for cam in rig:
        cameras[cam.name] = {"width": cam.width, "height": cam.height, "fx": float(cam.K[0, 0]),
                             "fy": float(cam.K[1, 1]), "cx": float(cam.K[0, 2]), "cy": float(cam.K[1, 2]),
                             "distortion": [float(d) for d in cam.dist], "center_m": [float(c) for c in cam.center]}
    centres = np.stack([cam.center for cam in rig])
    distances = np.linalg.norm(centres[:, None] - centres[None], axis=-1)[np.triu_indices(len(rig), 1)]
    return {"num_cameras": len(rig), "cameras": cameras,
            "distorted": [cam.name for cam in rig if np.any(cam.dist != 0)],
            "baseline_m": {"min": float(distances.min()), "max": float(distances.max())} if distances.size else None}


def write_pinhole_rig(rig: Rig, out: str | os.PathLike, alpha: float | None = None, *, overwrite: bool = False) -> Rig:
    """Write the undistorted (pinhole) rig of `rig` (see `mvtex.data.camera.undistorted_camera`);
    an existing file is replaced only with `overwrite` (`save_rig`)."""
    if alpha is not None and not 0.0 <= alpha <= 1.0:
        raise OptionError("alpha", f"must be in [0, 1], got {alpha}")
    pinhole = undistort_rig(rig, alpha)
    save_rig(pinhole, out, overwrite=overwrite)
    return pinhole


@writer("rig", inputs=lambda a: (a["rig"],))
def export_colmap(rig: Rig, out: str | os.PathLike, *, text: bool = False, overwrite: bool = False) -> Path:
    """Write a rig as a COLMAP model (PINHOLE cameras, one image `<camera>.png` each) into
    the folder `out` (written whole, then renamed in)."""

    out = Path(out)
    distorted = [cam.name for cam in rig if np.any(cam.dist != 0)]
    if distorted:
        raise InputError(rig.source, f"cameras {', '.join(distorted)} have distortion; COLMAP PINHOLE needs a pinhole rig: "
                         "mvtex rig RIG --undistort --out RIG2 (and undistort the images with mvtex undistort)")
    try:
        return write_rig(rig, out, text=text)
    except ValueError as err:  # skewed intrinsics
        raise InputError(rig.source, str(err)) from None


@writer("rig", file=True, inputs=lambda a: (a["model"],))
def import_colmap(model: str | os.PathLike, out: str | os.PathLike, *, overwrite: bool = False) -> Rig:
    """Read the cameras of a COLMAP model (PINHOLE or SIMPLE_PINHOLE) and write them as a rig."""

    rig = read_rig(model)
    save_rig(rig, out)
    return rig


@writer("rig", file=True)
def plot_rig_file(rig: Rig, out: str | os.PathLike, title: str = "", *, overwrite: bool = False) -> None:
    """A 3-D picture of the rig (frusta and names) as PNG."""

    plot_rig(rig, Path(out), title=title)


def _camera_images(folder: Path, rig: Rig) -> dict[str, list[tuple[Path, Path]]]:
    """camera -> [(input file, output path relative to the output folder)]."""
    plan: dict[str, list[tuple[Path, Path]]] = {}
    for entry in sorted(folder.iterdir()):
        if entry.name.startswith("."):
            continue
        if entry.is_dir():
            files = [p for p in sorted(entry.iterdir()) if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
            if not files:
                continue
            if entry.name not in rig.names:
                raise InputError(entry, f"no camera named {entry.name} in the rig (it has {', '.join(rig.names)})")
            plan.setdefault(entry.name, []).extend((p, Path(entry.name) / f"{p.stem}.png") for p in files)
        elif entry.is_file() and entry.suffix.lower() in IMAGE_SUFFIXES and entry.stem in rig.names:
            plan.setdefault(entry.stem, []).append((entry, Path(f"{entry.stem}.png")))
    if not plan:
        raise InputError(folder, "no images of the rig's cameras; expected IMAGES/<camera>/<name>.png|jpg or "
                         f"IMAGES/<camera>.png|jpg with cameras {', '.join(rig.names)}")
    return plan


@writer("undistort", inputs=lambda a: (a["images"],))
def undistort_folder(images: str | os.PathLike, rig: Rig, out: str | os.PathLike, *, alpha: float | None = None,
                     progress: bool = True, overwrite: bool = False) -> dict:
    """Undistort a folder of images with OpenCV so they compare with mvtex's renders.

    Input: `IMAGES/<camera>/<name>.png|jpg` or `IMAGES/<camera>.png|jpg`, camera names of
    the rig. Output `OUT` mirrors it (always PNG) and holds `rig.yaml`, the pinhole rig of
    the undistorted images (render with it), and `undistort.json`. `OUT` is written whole
    (to a temporary name first) and renamed into place.

    Returns:
        {"num_images", "cameras": {name: count}, "rig", "alpha"}.
    """

    images, out = Path(images), Path(out)
    if not images.is_dir():
        raise InputError(images, "image folder not found")
    if alpha is not None and not 0.0 <= alpha <= 1.0:
        raise OptionError("alpha", f"must be in [0, 1], got {alpha}")
    if out.resolve() == images.resolve() or images.resolve() in out.resolve().parents:
        raise InputError(out, f"is inside the image folder {images}; write the undistorted images elsewhere")
    plan = _camera_images(images, rig)
    pinhole = {cam.name: undistorted_camera(cam, alpha) for cam in rig}
    total = sum(len(v) for v in plan.values())
    with atomic_path(out) as tmp, tqdm(total=total, desc="undistort", unit="image", disable=not progress,
                                       file=sys.stderr) as bar:
        tmp.mkdir()
        for name, files in plan.items():
            for source, relative in files:
                image = read_image(source)  # RGB(A) or gray; the header's size checked before decoding
                try:
                    result = undistort_image(image, rig[name], pinhole[name])
                except ValueError as err:
                    raise InputError(source, str(err)) from None
                if result.ndim == 3 and result.shape[2] == 4:  # the PNG written is RGB
                    result = result[..., :3]
                save_png(tmp / relative, result)
                bar.update(1)
        save_rig(Rig(tuple(pinhole[cam.name] for cam in rig)), tmp / "rig.yaml")
        summary = {"format": UNDISTORT_FORMAT, "version": 1, "num_images": total,
                   "cameras": {name: len(files) for name, files in plan.items()}, "rig": "rig.yaml",
                   "alpha": alpha, "source": str(images)}
        write_json(tmp / "undistort.json", summary)
    return summary
