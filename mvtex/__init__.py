"""mvtex: texture sliding for learned cloth, multi-view reconstruction and COLMAP export.

The public API is what `import mvtex` gives; every command of the `mvtex` command line is
one of these calls::

    import mvtex

    dataset = mvtex.load_dataset("data/shirt")                     # mvtex synth / import wrote it
    rig = mvtex.load_rig("stereo")                                 # a rig YAML or a built-in rig
    mvtex.slide_dataset(dataset, rig, "ts", poses=dataset.select("test"),
                        options=mvtex.SlideOptions(subdiv=1))      # mvtex slide
    result = mvtex.evaluate(dataset, rig, "ts")                    # mvtex eval
    print(result.ratio_material)

Names are loaded on first use (PEP 562), so `import mvtex` needs nothing but the standard
library and the heavy libraries (moderngl, torch, OpenCV, pycolmap) load with the stage that
needs them. Type checkers read the same names from the import block below, the one list of
the public API (it runs only for them; at run time `__getattr__` reads it). The modules
behind them: docs/architecture.md.
"""

from __future__ import annotations

import ast
import importlib
from pathlib import Path
from typing import TYPE_CHECKING, Any

__version__ = "0.4.0"

if TYPE_CHECKING:
    # isort: off
    # (grouped by stage, in the order of the pipeline)
    # errors
    from mvtex.util.errors import InputError, OptionError, OutputError, NoGroundTruthError
    # cameras, rigs, datasets, texcoord sets
    from mvtex.data.camera import Camera, look_at
    from mvtex.data.rig import Rig, load_rig, save_rig
    from mvtex.data.dataset import Dataset, load_dataset, save_dataset
    from mvtex.data.importer import import_sequences
    from mvtex.data.texcoords import TexcoordSet, open_texcoords, save_texcoords
    # the built-in datasets
    from mvtex.synth.options import SynthOptions
    from mvtex.synth.generate import SynthResult, synthesize, write_synth
    # rendering
    from mvtex.render.context import GLContext
    from mvtex.render.raster import Raster, rasterize, rasterize_uv, interpolate
    from mvtex.render.shading import render_textured
    from mvtex.render.pose import render_pose
    # texture sliding
    from mvtex.sliding.options import SlideOptions
    from mvtex.sliding.pose import slide_pose
    from mvtex.sliding.dataset import slide_dataset
    from mvtex.sliding.fill import fill
    # evaluation
    from mvtex.evaluation.evaluate import evaluate, Evaluation
    from mvtex.evaluation.material import MaterialMap
    # reconstruction
    from mvtex.recon.options import ReconOptions
    from mvtex.recon.triangulate import Reconstruction, reconstruct
    from mvtex.recon.report import ReconReport
    from mvtex.recon.pose import triangulate_pose
    from mvtex.recon.geometry import project_points, triangulate_points
    # novel views and previews
    from mvtex.views.options import ViewOptions, PreviewOptions, ExportOptions
    from mvtex.views.cameras import interpolate_camera
    from mvtex.views.novel import novel_views
    from mvtex.views.preview import stereo_preview
    from mvtex.views.scene import export_scene
    # calibration
    from mvtex.calibration.board import BoardSpec, parse_board_spec, write_board_png
    from mvtex.calibration.options import CalibrateOptions
    from mvtex.calibration.calibrate import calibrate
    from mvtex.calibration.output import calibrate_folder
    # texture sliding models
    from mvtex.tsnn.options import TrainOptions
    from mvtex.tsnn.modeldir import TrainResult, TrainedCameras
    from mvtex.tsnn.train import train
    from mvtex.tsnn.cameras import train_cameras, train_models
    from mvtex.tsnn.predict import predict, load_model
    from mvtex.tsnn.config import ModelConfig
    from mvtex.tsnn.options import GeometryOptions, CorrectOptions
    from mvtex.tsnn.corrector import GeometryResult, train_geometry, load_corrector
    from mvtex.tsnn.correct import correct, CorrectResult
    # applications
    from mvtex.apps.bench import run_bench
    from mvtex.apps.options import DemoOptions
    from mvtex.apps.demo import run_demo
    # isort: on

__all__ = [
    "__version__",
    "InputError",
    "OptionError",
    "OutputError",
    "NoGroundTruthError",
    "Camera",
    "look_at",
    "Rig",
    "load_rig",
    "save_rig",
    "Dataset",
    "load_dataset",
    "save_dataset",
    "import_sequences",
    "TexcoordSet",
    "open_texcoords",
    "save_texcoords",
    "SynthOptions",
    "SynthResult",
    "synthesize",
    "write_synth",
    "GLContext",
    "Raster",
    "rasterize",
    "rasterize_uv",
    "interpolate",
    "render_textured",
    "render_pose",
    "SlideOptions",
    "slide_pose",
    "slide_dataset",
    "fill",
    "evaluate",
    "Evaluation",
    "MaterialMap",
    "ReconOptions",
    "Reconstruction",
    "reconstruct",
    "ReconReport",
    "triangulate_pose",
    "project_points",
    "triangulate_points",
    "ViewOptions",
    "PreviewOptions",
    "ExportOptions",
    "interpolate_camera",
    "novel_views",
    "stereo_preview",
    "export_scene",
    "BoardSpec",
    "parse_board_spec",
    "write_board_png",
    "CalibrateOptions",
    "calibrate",
    "calibrate_folder",
    "TrainOptions",
    "TrainResult",
    "TrainedCameras",
    "train",
    "train_cameras",
    "train_models",
    "predict",
    "load_model",
    "ModelConfig",
    "GeometryOptions",
    "CorrectOptions",
    "GeometryResult",
    "train_geometry",
    "load_corrector",
    "correct",
    "CorrectResult",
    "run_bench",
    "DemoOptions",
    "run_demo",
]


def _read_api() -> dict[str, str]:
    """public name -> the module that defines it, read from the `TYPE_CHECKING` block of
    this file."""
    tree = ast.parse(Path(__file__).read_text(encoding="utf-8"))
    block = next(node for node in tree.body
                 if isinstance(node, ast.If) and getattr(node.test, "id", "") == "TYPE_CHECKING")
    return {alias.name: node.module for node in block.body if isinstance(node, ast.ImportFrom)
            for alias in node.names if node.module}


_API: dict[str, str] = {}


def __getattr__(name: str) -> Any:
    if not _API:
        _API.update(_read_api())
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'mvtex' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # the next access is a plain attribute
    return value


def __dir__() -> list[str]:
    return sorted(__all__)
