"""Images given to `calibrate` and `undistort`: finding them, their size from the header
before anything is decoded, and decoding them without a word on stderr.

Pictures are decoded by Pillow, whose decoders raise instead of printing (libpng's and
libjpeg's own warnings never reach the terminal) and which refuses a truncated file instead
of returning the part it read. A 16-bit colour PNG, which Pillow would reduce to 8 bits, is
decoded by OpenCV after Pillow has read it whole, with whatever libpng says kept off stderr.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import threading
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from mvtex.data.camera import MAX_IMAGE_SIZE, check_camera_name
from mvtex.util.errors import InputError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class CameraImages:
    """One camera's images: frame name -> file, all of one size."""

    name: str
    files: dict[str, Path]


def find_images(folder: str | os.PathLike) -> list[CameraImages]:
    """The cameras (sub-folders, sorted by name) and their frames under `folder`.

    Raises:
        InputError: no such folder, no camera folder with images, or two files of one
            camera with the same frame name.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "image folder not found")
    cameras = []
    seen: dict[str, str] = {}
    for sub in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
        # A camera folder's name becomes the camera's name: checked before any detection runs.
        try:
            check_camera_name(sub.name)
        except ValueError as err:
            raise InputError(sub, f"{err}; rename the folder") from None
        if sub.name.lower() in seen:
            raise InputError(sub, f"camera folders {seen[sub.name.lower()]!r} and {sub.name!r} differ only in case "
                             "(camera names must be unique ignoring case)")
        seen[sub.name.lower()] = sub.name
        files: dict[str, Path] = {}
        for path in sorted(sub.iterdir()):
            if path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES:
                if path.stem in files:
                    raise InputError(path, f"two images of frame {path.stem!r} ({files[path.stem].name}, {path.name})")
                files[path.stem] = path
        if files:
            cameras.append(CameraImages(sub.name, files))
    if not cameras:
        raise InputError(folder, "no images found; expected IMAGES/<camera>/<frame>.png or .jpg")
    return cameras


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of a PNG or JPEG from its header, without decoding the pixels (Pillow
    opens lazily).

    Raises:
        InputError: naming the file when it is not a readable image, or larger than
            `mvtex.data.camera.MAX_IMAGE_SIZE` on a side (checked before any memory is taken).
    """
    from PIL import Image, UnidentifiedImageError  # noqa: PLC0415 (loaded on use)

    try:
        with open(path, "rb") as file:
            head = file.read(24)
    except OSError as err:
        raise InputError(path, f"cannot be read ({err.strerror or err})") from None
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":  # the size is in the first chunk
        width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    else:
        try:
            with Image.open(path) as image:
                width, height = image.size
        except Image.DecompressionBombError:  # Pillow's own bound (far above ours) says so first
            raise InputError(path, f"image larger than {MAX_IMAGE_SIZE}x{MAX_IMAGE_SIZE} pixels") from None
        except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as err:
            raise InputError(path, f"cannot be read as an image ({err.__class__.__name__})") from None
    if not (1 <= width <= MAX_IMAGE_SIZE and 1 <= height <= MAX_IMAGE_SIZE):
        raise InputError(path, f"image is {width}x{height}: mvtex reads images of 1..{MAX_IMAGE_SIZE} pixels "
                         "a side")
    return int(width), int(height)


def camera_image_size(images: CameraImages) -> tuple[int, int]:
    """The (width, height) of one camera's images, from their headers: the size most of them
    have. An image of another size is refused, naming it (not the first of the others).

    Raises:
        InputError: naming the odd image, or an unreadable one.
    """
    sizes = {frame: image_size(path) for frame, path in images.files.items()}
    size, count = Counter(sizes.values()).most_common(1)[0]
    for frame, other in sizes.items():
        if other != size:
            raise InputError(images.files[frame], f"image is {other[0]}x{other[1]}, camera {images.name}'s other "
                             f"images are {size[0]}x{size[1]} ({count} of {len(sizes)})")
    return size


_STDERR = threading.Lock()


@contextlib.contextmanager
def _stderr_kept() -> Iterator[list[str]]:
    """Keep what native code writes to file descriptor 2 off stderr for the block; the
    list yielded holds it afterwards."""
    said: list[str] = []
    with _STDERR, tempfile.TemporaryFile() as sink:
        saved = os.dup(2)
        try:
            os.dup2(sink.fileno(), 2)
            yield said
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            said.append(sink.read().decode(errors="replace"))


def _open(path: Path, gray: bool = False):
    """The image of `path` decoded whole by Pillow, or InputError naming it; with `gray`, a
    JPEG is decoded to its luma directly (as libjpeg does for OpenCV's gray reads)."""
    from PIL import Image, UnidentifiedImageError  # noqa: PLC0415 (loaded on use)

    image_size(path)  # the header's size is checked before anything is decoded
    try:
        image = Image.open(path)
        if gray and image.format == "JPEG":
            image.draft("L", image.size)
        image.load()  # a truncated or corrupt file raises here
        return image
    except Image.DecompressionBombError:
        raise InputError(path, f"image larger than {MAX_IMAGE_SIZE}x{MAX_IMAGE_SIZE} pixels") from None
    except UnidentifiedImageError:
        raise InputError(path, "cannot be read as an image (not a PNG or JPEG, or a damaged one)") from None
    except (OSError, ValueError, SyntaxError, EOFError) as err:
        detail = str(err).strip().splitlines()[0] if str(err).strip() else err.__class__.__name__
        raise InputError(path, f"cannot be read as an image ({detail})") from None


def read_gray(path: str | os.PathLike) -> np.ndarray:
    """A gray (H,W) uint8 image (as `cv2.imread(..., IMREAD_GRAYSCALE)` gives: ITU-R 601
    luma, 16 bits scaled to 8, the EXIF orientation applied).

    Raises:
        InputError: naming the file: unreadable, truncated, larger than MAX_IMAGE_SIZE a
            side (from the header, before decoding).
    """
    from PIL import ImageOps  # noqa: PLC0415 (loaded on use)

    path = Path(path)
    image = ImageOps.exif_transpose(_open(path, gray=True))
    if image.mode in ("I;16", "I;16B", "I;16L", "I"):
        return (np.clip(np.asarray(image, np.int64), 0, 65535) >> 8).astype(np.uint8)
    gray = np.asarray(image.convert("L"))
    if gray.size == 0:
        raise InputError(path, "cannot be read as an image (no pixels)")
    return np.ascontiguousarray(gray)


def read_image(path: str | os.PathLike) -> np.ndarray:
    """An image as stored: (H,W) gray or (H,W,3) RGB / (H,W,4) RGBA, uint8 or uint16 (no
    orientation applied).

    Raises:
        InputError: naming the file: unreadable, truncated, larger than MAX_IMAGE_SIZE a side.
    """
    path = Path(path)
    image = _open(path)
    with open(path, "rb") as file:
        head = file.read(26)
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[24] == 16 and head[25] in (2, 6):
        return _read_16bit_color(path)  # Pillow would reduce it to 8 bits
    if image.mode in ("I;16", "I;16B", "I;16L"):
        return np.asarray(image).astype(np.uint16)
    if image.mode == "I":
        return np.clip(np.asarray(image, np.int64), 0, 65535).astype(np.uint16)
    if image.mode in ("1", "L"):
        return np.asarray(image.convert("L"))
    alpha = image.mode in ("RGBA", "LA", "PA") or (image.mode == "P" and "transparency" in image.info)
    return np.asarray(image.convert("RGBA" if alpha else "RGB"))


def _read_16bit_color(path: Path) -> np.ndarray:
    import cv2  # noqa: PLC0415 (loaded on use)

    data = np.fromfile(path, np.uint8)
    with _stderr_kept():
        image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if image is None or image.ndim != 3:
        raise InputError(path, "cannot be read as an image")
    return np.ascontiguousarray(image[..., [2, 1, 0, 3][:image.shape[2]]])  # BGR(A) -> RGB(A)
