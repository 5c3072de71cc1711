"""ChArUco calibration boards: the SPEC string, the printable image and corner detection
(`mvtex.calibration.synthetic` draws the board seen by a camera).

A board SPEC reads `charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT`, e.g.
`charuco:9x6:0.05:0.0375:DICT_5X5_100`: COLS x ROWS chessboard squares of SQUARE_M meters,
ArUco markers of MARKER_M meters from the OpenCV dictionary DICT (`cv2.aruco.DICT_*`).

Board frame (OpenCV's `CharucoBoard`): origin at the board's top-left outer corner, x along
the columns, y down the rows, z = 0 on the board (into the board, away from a camera that
sees its printed side). Chessboard corner `i` (the ids `CharucoDetector` reports) is at
((i mod (COLS-1)) + 1, (i div (COLS-1)) + 1) * SQUARE_M.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from mvtex.util.checks import as_path, check_instance
from mvtex.util.errors import InputError, OptionError
from mvtex.util.options import NO_DEFAULT, Options, knob
from mvtex.util.output import atomic_path, writer

SPEC_PATTERN = re.compile(r"^charuco:(\d+)x(\d+):([0-9.eE+-]+):([0-9.eE+-]+):(DICT_\w+)$")


SPEC_FORMAT = "charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT (e.g. charuco:9x6:0.05:0.0375:DICT_5X5_100)"


PNG_SOFTWARE = "mvtex board"


MM_PER_INCH = 25.4
MAX_BOARD_PIXELS = 32768  # side of the printable image (a 1.1 m board at 750 dpi)


@dataclass(frozen=True)
class BoardSpec(Options):
    """A ChArUco board.

    Attributes:
        cols, rows: number of chessboard squares along x and y (each >= 3).
        square_m: side of a chessboard square in meters.
        marker_m: side of an ArUco marker in meters (< square_m).
        dictionary: name of an OpenCV predefined dictionary, e.g. "DICT_5X5_100".
    """

    cols: int = knob(NO_DEFAULT, "chessboard squares along x", low=3, flag=False)
    rows: int = knob(NO_DEFAULT, "chessboard squares along y", low=3, flag=False)
    square_m: float = knob(NO_DEFAULT, "side of a chessboard square", unit="m", low=0, low_open=True, flag=False)
    marker_m: float = knob(NO_DEFAULT, "side of an ArUco marker", unit="m", low=0, low_open=True, flag=False)
    dictionary: str = knob(NO_DEFAULT, "an OpenCV predefined dictionary, e.g. DICT_5X5_100", flag=False)

    def validate(self) -> None:
        import cv2  # noqa: PLC0415 (loaded on use)

        if not 0 < self.marker_m < self.square_m:
            raise OptionError("marker_m", f"must be in (0, square_m), got square_m {self.square_m:g} and "
                              f"marker_m {self.marker_m:g}")
        if not self.dictionary.startswith("DICT_") or not isinstance(getattr(cv2.aruco, self.dictionary, None), int):
            raise OptionError("dictionary", f"must be an OpenCV ArUco dictionary (cv2.aruco.DICT_*), got {self.dictionary!r}")

    def __str__(self) -> str:
        return f"charuco:{self.cols}x{self.rows}:{self.square_m:g}:{self.marker_m:g}:{self.dictionary}"

    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) of the chessboard area in meters."""
        return self.cols * self.square_m, self.rows * self.square_m

    @property
    def num_corners(self) -> int:
        """Number of inner chessboard corners, (COLS-1)(ROWS-1)."""
        return (self.cols - 1) * (self.rows - 1)

    @cached_property
    def cv_board(self):
        """The `cv2.aruco.CharucoBoard`."""
        import cv2  # noqa: PLC0415 (loaded on use)

        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_m, self.marker_m, dictionary)

    @property
    def corners(self) -> np.ndarray:
        """(num_corners, 3) float64 chessboard corners in the board frame, indexed by corner id."""
        return np.asarray(self.cv_board.getChessboardCorners(), dtype=np.float64).reshape(-1, 3)


def parse_board_spec(text: str) -> BoardSpec:
    """Parse `charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT`; anything else raises InputError."""
    import cv2  # noqa: PLC0415 (loaded on use)

    match = SPEC_PATTERN.match(str(text).strip())
    if not match:
        raise InputError(None, f"board SPEC {text!r} does not parse; expected {SPEC_FORMAT}")
    cols, rows = int(match[1]), int(match[2])
    try:
        square, marker = float(match[3]), float(match[4])
    except ValueError:
        raise InputError(None, f"board SPEC {text!r}: square and marker sizes must be numbers in meters") from None
    name = match[5]
    if cols < 3 or rows < 3:
        raise InputError(None, f"board SPEC {text!r}: needs at least 3x3 squares, got {cols}x{rows}")
    if not (np.isfinite(square) and np.isfinite(marker) and 0 < marker < square):
        raise InputError(None, f"board SPEC {text!r}: needs 0 < MARKER_M < SQUARE_M, got SQUARE_M {square:g} and "
                         f"MARKER_M {marker:g}")
    if not hasattr(cv2.aruco, name):
        raise InputError(None, f"board SPEC {text!r}: unknown dictionary {name} (OpenCV's cv2.aruco.DICT_*, "
                         "e.g. DICT_4X4_50, DICT_5X5_100, DICT_6X6_250)")
    try:
        size = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)).bytesList.shape[0]
    except (cv2.error, TypeError):
        raise InputError(None, f"board SPEC {text!r}: {name} is not a predefined ArUco dictionary") from None
    needed = (cols * rows) // 2
    if needed > size:
        raise InputError(None, f"board SPEC {text!r}: {cols}x{rows} squares need {needed} markers, {name} has {size}")
    return BoardSpec(cols, rows, square, marker, name)


def board_image(spec: BoardSpec, pixels_per_square: int, margin_px: int = 0) -> np.ndarray:
    """The board as a gray image, white margin around it.

    Args:
        spec: the board.
        pixels_per_square: side of a chessboard square in pixels.
        margin_px: white border added on every side.

    Returns:
        (rows*pps + 2*margin, cols*pps + 2*margin) uint8. Board point (x, y) in meters lies at
        OpenCV pixel (x/square*pps + margin - 0.5, y/square*pps + margin - 0.5): square
        edges fall on pixel edges.
    """
    pps = int(pixels_per_square)
    if pps < 8:
        raise ValueError(f"pixels_per_square must be >= 8, got {pps}")
    size = (spec.cols * pps + 2 * margin_px, spec.rows * pps + 2 * margin_px)
    return np.asarray(spec.cv_board.generateImage(size, marginSize=int(margin_px), borderBits=1), dtype=np.uint8)


@writer("board", out="path", file=True)
def write_board_png(spec: BoardSpec, path: str | os.PathLike, *, dpi: float | None = None,
                    pixels_per_square: int | None = None, margin_m: float | None = None,
                    overwrite: bool = False) -> dict:
    """Write the printable board as a PNG that records its print resolution.

    Give `dpi` (pixels per inch of the print; default 300) or `pixels_per_square`. The PNG
    carries its dpi (pHYs), so printing it at 100 % scale gives squares of `square_m`; the
    margin (default: half a square, at least 10 mm) shows the SPEC in small print. The file
    is written under a temporary name and renamed into place.

    Returns:
        {"path", "spec", "pixels_per_square", "dpi", "width_px", "height_px", "width_mm", "height_mm"}.
    """

    check_instance(spec, BoardSpec, "spec")
    path = as_path(path, "path")
    for key, value in (("dpi", dpi), ("pixels_per_square", pixels_per_square), ("margin_m", margin_m)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating))
                                  or not np.isfinite(value)):
            raise OptionError(key, f"must be a finite number, got {value!r:.60}")
    if pixels_per_square is not None and not float(pixels_per_square).is_integer():
        raise OptionError("pixels_per_square", f"must be an integer, got {pixels_per_square!r}")
    import cv2  # noqa: PLC0415 (loaded on use)
    from PIL import Image, PngImagePlugin  # noqa: PLC0415 (loaded on use)

    path = Path(path)
    if dpi is not None and pixels_per_square is not None:
        raise OptionError("dpi", "and pixels_per_square: give one, not both")
    if pixels_per_square is None:
        dpi = 300.0 if dpi is None else float(dpi)
        if not (np.isfinite(dpi) and dpi > 0):
            raise OptionError("dpi", f"must be positive, got {dpi}")
        pixels_per_square = int(round(spec.square_m * 1000 / MM_PER_INCH * dpi))
    else:
        dpi = pixels_per_square / (spec.square_m * 1000 / MM_PER_INCH)
    if pixels_per_square < 8:
        raise OptionError("pixels_per_square", f"must be at least 8 to print the markers, got {pixels_per_square}")
    margin_m = max(spec.square_m / 2, 0.010) if margin_m is None else float(margin_m)
    if not (np.isfinite(margin_m) and margin_m >= 0):
        raise OptionError("margin_m", f"must be a finite number >= 0, got {margin_m}")
    margin_px = int(round(margin_m * 1000 / MM_PER_INCH * dpi))
    side = max(spec.cols, spec.rows) * pixels_per_square + 2 * margin_px
    if side > MAX_BOARD_PIXELS:  # checked before OpenCV allocates the image
        raise OptionError("pixels_per_square", f"{pixels_per_square} makes a board image of {side} pixels a side, more "
                          f"than {MAX_BOARD_PIXELS}; lower it (or the dpi)")
    image = board_image(spec, pixels_per_square, margin_px)
    text = f"{spec}   square {spec.square_m * 1000:g} mm   print at {dpi:.0f} dpi, 100 %"
    scale = margin_px * 0.35 / 22.0
    if scale >= 0.25:
        (w, h), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
        if w < image.shape[1] - 2 * margin_px:
            y = image.shape[0] - margin_px // 2 + h // 2
            cv2.putText(image, text, (margin_px, y), cv2.FONT_HERSHEY_SIMPLEX, scale, 96,
                        max(1, int(round(scale * 2))), cv2.LINE_AA)
    info = PngImagePlugin.PngInfo()
    info.add_text("Software", PNG_SOFTWARE)
    info.add_text("Description", str(spec))
    with atomic_path(path) as tmp:
        Image.fromarray(image).save(tmp, format="PNG", dpi=(dpi, dpi), pnginfo=info)
    height, width = image.shape
    return {"path": str(path), "spec": str(spec), "pixels_per_square": int(pixels_per_square), "dpi": float(dpi),
            "width_px": int(width), "height_px": int(height),
            "width_mm": width / dpi * MM_PER_INCH, "height_mm": height / dpi * MM_PER_INCH}


@dataclass(frozen=True)
class Detection:
    """Chessboard corners of a board found in one image.

    Attributes:
        ids: (k,) int32 corner ids (rows of `BoardSpec.corners`), ascending.
        pixels: (k,2) float64 OpenCV pixel coordinates, sub-pixel.
    """

    ids: np.ndarray
    pixels: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


class BoardDetector:
    """`cv2.aruco.CharucoDetector` for one board, made once and reused over images."""

    def __init__(self, spec: BoardSpec):
        import cv2  # noqa: PLC0415 (loaded on use)

        self.spec = spec
        charuco = cv2.aruco.CharucoParameters()
        detector = cv2.aruco.DetectorParameters()
        detector.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        self._detector = cv2.aruco.CharucoDetector(spec.cv_board, charuco, detector)

    def detect(self, image: np.ndarray) -> Detection:
        """Detect the chessboard corners in a gray (H,W) or colour (H,W,3) uint8 image."""
        import cv2  # noqa: PLC0415 (loaded on use)

        image = np.asarray(image)
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        corners, ids, _, _ = self._detector.detectBoard(image)
        if ids is None or len(ids) == 0:
            return Detection(np.zeros(0, np.int32), np.zeros((0, 2)))
        ids = np.asarray(ids, dtype=np.int32).reshape(-1)
        pixels = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
        order = np.argsort(ids)
        return Detection(ids[order], pixels[order])
