"""The public API: `import mvtex` gives these names and no more, loads no heavy library,
and each name is the library object the stage module defines."""

from __future__ import annotations

import importlib
import subprocess
import sys

import mvtex

PUBLIC = {
    "__version__", "InputError", "OptionError", "OutputError", "NoGroundTruthError",
    "Camera", "look_at", "Rig", "load_rig", "save_rig", "Dataset", "load_dataset", "save_dataset", "import_sequences",
    "TexcoordSet", "open_texcoords", "save_texcoords",
    "SynthOptions", "SynthResult", "synthesize", "write_synth",
    "GLContext", "Raster", "rasterize", "rasterize_uv", "interpolate", "render_textured", "render_pose",
    "SlideOptions", "slide_pose", "slide_dataset", "fill",
    "evaluate", "Evaluation", "MaterialMap",
    "ReconOptions", "Reconstruction", "ReconReport", "reconstruct", "triangulate_pose", "project_points",
    "triangulate_points",
    "ViewOptions", "interpolate_camera", "novel_views", "PreviewOptions", "stereo_preview", "ExportOptions",
    "export_scene",
    "BoardSpec", "parse_board_spec", "write_board_png", "CalibrateOptions", "calibrate", "calibrate_folder",
    "TrainOptions", "TrainResult", "TrainedCameras", "train", "train_cameras", "train_models", "predict", "load_model",
    "ModelConfig", "GeometryOptions", "GeometryResult", "train_geometry", "load_corrector", "correct", "CorrectOptions",
    "CorrectResult",
    "run_bench", "DemoOptions", "run_demo",
}


def test_the_public_names_are_these():
    assert set(mvtex.__all__) == PUBLIC
    assert set(dir(mvtex)) >= PUBLIC


def test_all_lists_the_typed_import_block_once():
    """`__all__` and the block type checkers read name the same objects, each once."""
    api = mvtex._read_api()
    assert mvtex.__all__ == ["__version__", *api]
    assert len(set(mvtex.__all__)) == len(mvtex.__all__)


def test_every_public_name_is_the_stage_modules_object():
    for name in sorted(PUBLIC - {"__version__"}):
        value = getattr(mvtex, name)
        module = importlib.import_module(mvtex._read_api()[name])
        assert getattr(module, name) is value, name
        assert value.__module__ == module.__name__, name  # defined there, not re-exported


def test_import_mvtex_loads_no_heavy_library():
    heavy = ["numpy", "scipy", "moderngl", "torch", "cv2", "pycolmap", "dask", "trimesh", "skimage", "numba"]
    code = f"import sys, mvtex; print([m for m in {heavy!r} if m in sys.modules])"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_an_unknown_name_is_an_attribute_error():
    import pytest

    with pytest.raises(AttributeError, match="no attribute 'slide'"):
        mvtex.slide


def test_the_installed_version_is_the_package_version():
    from importlib.metadata import version

    import mvtex

    assert version("mvtex") == mvtex.__version__
