"""Files shipped with mvtex: GLSL shaders (`shaders/`) and example rigs (`calib/`).

Installed, they are the packages `mvtex.shaders` and `mvtex.calib`; in a source checkout
that is imported without installing, they are the folders beside `mvtex/`.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path


def resource_path(folder: str, name: str) -> Path:
    """Path of a shipped file, e.g. resource_path("shaders", "raster.vert.glsl")."""
    try:
        return Path(str(resources.files(f"mvtex.{folder}").joinpath(name)))
    except ModuleNotFoundError:
        return Path(__file__).resolve().parents[2] / folder / name
