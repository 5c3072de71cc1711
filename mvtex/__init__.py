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
needs them. The modules behind them: docs/architecture.md.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.3.0"

# public name -> the module that defines it
_API = {
    # errors
    "InputError": "mvtex.util.errors", "OptionError": "mvtex.util.errors", "OutputError": "mvtex.util.errors",
    # cameras, rigs, datasets, texcoord sets
    "Camera": "mvtex.data.camera", "look_at": "mvtex.data.camera",
    "Rig": "mvtex.data.rig", "load_rig": "mvtex.data.rig", "save_rig": "mvtex.data.rig",
    "Dataset": "mvtex.data.dataset", "load_dataset": "mvtex.data.dataset", "save_dataset": "mvtex.data.dataset",
    "import_sequences": "mvtex.data.importer",
    "TexcoordSet": "mvtex.data.texcoords", "open_texcoords": "mvtex.data.texcoords",
    "save_texcoords": "mvtex.data.texcoords",
    # the built-in datasets
    "SynthOptions": "mvtex.synth.generate", "SynthResult": "mvtex.synth.generate",
    "synthesize": "mvtex.synth.generate", "write_synth": "mvtex.synth.generate",
    # rendering
    "GLContext": "mvtex.render.context", "Raster": "mvtex.render.raster", "rasterize": "mvtex.render.raster",
    "rasterize_uv": "mvtex.render.raster", "interpolate": "mvtex.render.raster",
    "render_textured": "mvtex.render.shading", "render_pose": "mvtex.render.pose",
    # texture sliding
    "SlideOptions": "mvtex.sliding.options", "slide_pose": "mvtex.sliding.pose",
    "slide_dataset": "mvtex.sliding.dataset", "fill": "mvtex.sliding.fill",
    # evaluation
    "evaluate": "mvtex.evaluation.evaluate", "Evaluation": "mvtex.evaluation.evaluate",
    "MaterialMap": "mvtex.evaluation.material",
    # reconstruction
    "ReconOptions": "mvtex.recon.options", "Reconstruction": "mvtex.recon.triangulate",
    "ReconReport": "mvtex.recon.report",
    "reconstruct": "mvtex.recon.triangulate", "triangulate_pose": "mvtex.recon.pose",
    "project_points": "mvtex.recon.geometry", "triangulate_points": "mvtex.recon.geometry",
    # novel views and previews
    "ViewOptions": "mvtex.views.synthesizer", "interpolate_camera": "mvtex.views.cameras",
    "novel_views": "mvtex.views.novel", "PreviewOptions": "mvtex.views.preview",
    "stereo_preview": "mvtex.views.preview",
    # calibration
    "BoardSpec": "mvtex.calibration.board", "parse_board_spec": "mvtex.calibration.board",
    "write_board_png": "mvtex.calibration.board", "CalibrateOptions": "mvtex.calibration.calibrate",
    "calibrate": "mvtex.calibration.calibrate", "calibrate_folder": "mvtex.calibration.output",
    # texture sliding models
    "TrainOptions": "mvtex.tsnn.train", "TrainResult": "mvtex.tsnn.modeldir", "TrainedCameras": "mvtex.tsnn.modeldir",
    "train": "mvtex.tsnn.train", "train_cameras": "mvtex.tsnn.cameras",
    "predict": "mvtex.tsnn.predict", "load_model": "mvtex.tsnn.predict",
    # the geometry corrector
    "GeometryOptions": "mvtex.tsnn.corrector", "GeometryResult": "mvtex.tsnn.corrector",
    "train_geometry": "mvtex.tsnn.corrector", "load_corrector": "mvtex.tsnn.corrector",
    "correct": "mvtex.tsnn.correct", "CorrectOptions": "mvtex.tsnn.correct", "CorrectResult": "mvtex.tsnn.correct",
    # applications
    "run_bench": "mvtex.apps.bench", "DemoOptions": "mvtex.apps.demo", "run_demo": "mvtex.apps.demo",
}

__all__ = ["__version__", *_API]


def __getattr__(name: str) -> Any:
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'mvtex' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # the next access is a plain attribute
    return value


def __dir__() -> list[str]:
    return sorted(__all__)
