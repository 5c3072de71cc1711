"""The public API fuzzed over its arguments' types, shapes and values: every function and
options class of `import mvtex` is called with one argument replaced by something hostile
(None, a number where an array belongs, a ragged list, NaN, a dict, an array of the wrong
shape, ...), the others valid. Whatever it gets, it returns or raises a typed mvtex error
(`mvtex.InputError`, of which `OptionError` is one) naming the argument; never an
IndexError, KeyError, AttributeError or TypeError from inside, never a hang."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import array_shapes, arrays

import mvtex

FUZZ = settings(max_examples=30, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

_numbers = st.one_of(st.integers(-10**6, 10**6), st.floats(allow_nan=True, allow_infinity=True),
                     st.sampled_from([0, -1, 1e300, float("nan"), float("inf"), -float("inf"), 2**63]))
# Values that are no file path: a path argument given one of these must be refused.
NOT_TEXT = st.one_of(
    st.none(), st.booleans(), _numbers, st.binary(max_size=6),
    st.lists(st.integers(-3, 3), max_size=4), st.lists(st.lists(st.floats(-1, 1), max_size=3), max_size=3),
    st.dictionaries(st.text(max_size=3), st.integers(-2, 2), max_size=2),
    arrays(np.float64, array_shapes(min_dims=0, max_dims=3, max_side=4),
           elements=st.floats(allow_nan=True, allow_infinity=True)),
    arrays(np.int64, array_shapes(min_dims=1, max_dims=2, max_side=4), elements=st.integers(-5, 5)),
    st.sampled_from([object(), [[1, 2], [3]], (1, "a"), {1, 2}, np.array(["a", "b"]), np.zeros((0, 3)),
                     np.full((2, 3), np.nan), b"\x00", [None], {"a": None}]),
)
HOSTILE = st.one_of(NOT_TEXT, st.text(max_size=8), st.sampled_from(["", "..", "/", "a/b", "nan", "-1", "x" * 70]))

K = np.array([[80.0, 0, 31.5], [0, 80.0, 23.5], [0, 0, 1]])


class Sandbox:
    """Valid arguments, built once per test from the shared fixtures."""

    def __init__(self, root: Path, tiny_dataset, front_rig, slid_sheet):
        self.root = root
        self.dataset = mvtex.load_dataset(tiny_dataset)
        self.rig = front_rig
        self.tc = mvtex.open_texcoords(slid_sheet)
        self.count = itertools.count()
        ds = self.dataset
        self.mesh = dict(faces=np.asarray(ds.faces), uv=np.asarray(ds.uv))

    def out(self, what: str) -> str:
        return str(self.root / f"{what}{next(self.count)}")


def targets(sb: Sandbox) -> dict:
    """name -> (function, valid keyword arguments (a callable of the sandbox), argument -> strategy)."""
    ds, rig, tc = sb.dataset, sb.rig, sb.tc
    n, k = ds.num_vertices, ds.num_poses
    cam = rig.cameras[0]
    dtc = {c: np.zeros((1, len(tc.uv), 2), np.float32) for c in ("a",)}
    board = mvtex.parse_board_spec("charuco:5x4:0.04:0.03:DICT_4X4_50")
    every = lambda *names, s=HOSTILE: {name: s for name in names}  # noqa: E731
    return {
        "Camera": (mvtex.Camera, lambda: dict(name="a", width=64, height=48, K=K, R=np.eye(3), t=[0, 0, 1.0]),
                   every("name", "width", "height", "K", "R", "t", "dist")),
        "look_at": (mvtex.look_at, lambda: dict(name="a", center=(0, 0, 1.0), target=(0, 0, 0), width=64, height=48,
                                                focal=80.0),
                    every("name", "center", "target", "width", "height", "focal", "up")),
        "Rig": (mvtex.Rig, lambda: dict(cameras=(cam,)), every("cameras")),
        "load_rig": (mvtex.load_rig, lambda: dict(path=sb.out("rig")), every("path")),
        "save_rig": (mvtex.save_rig, lambda: dict(rig=rig, path=sb.out("rig") + ".yaml"),
                     {"rig": HOSTILE, "path": NOT_TEXT}),
        "load_dataset": (mvtex.load_dataset, lambda: dict(path=sb.out("ds")), every("path")),
        "save_dataset": (mvtex.save_dataset,
                         lambda: dict(path=sb.out("ds"), faces=ds.faces, uv=ds.uv, gt=np.asarray(ds.gt[:2]),
                                      inferred=np.asarray(ds.inferred[:2]), poses=np.asarray(ds.poses[:2])),
                         {"path": NOT_TEXT, **every("faces", "uv", "gt", "inferred", "poses", "name", "rest", "split",
                                                    "body_faces", "body")}),
        "open_texcoords": (mvtex.open_texcoords, lambda: dict(path=tc.path, num_vertices=n, num_poses=k),
                           {"path": NOT_TEXT, **every("num_vertices", "num_poses")}),
        "save_texcoords": (mvtex.save_texcoords,
                           lambda: dict(path=sb.out("tc"), faces=tc.faces, uv=tc.uv, parent=tc.parent, source="ts",
                                        subdiv=tc.subdiv, poses=[0], displacement=dict(dtc),
                                        assigned={"a": np.ones((1, len(tc.uv)), bool)}),
                           {"path": NOT_TEXT, **every("faces", "uv", "parent", "source", "subdiv", "poses",
                                                      "displacement", "assigned")}),
        "project_points": (mvtex.project_points, lambda: dict(cameras=list(rig), points=np.zeros((3, 3))),
                           every("cameras", "points")),
        "triangulate_points": (mvtex.triangulate_points,
                               lambda: dict(cameras=list(rig), pixels=np.full((2, 2, 2), 30.0), weights=np.ones((2, 2))),
                               every("cameras", "pixels", "weights", "iterations", "min_angle_deg")),
        "interpolate_camera": (mvtex.interpolate_camera, lambda: dict(rig=rig, weights={"a": 0.5, "b": 0.5}, name="v"),
                               every("rig", "weights", "name")),
        "parse_board_spec": (mvtex.parse_board_spec, lambda: dict(text="charuco:5x4:0.04:0.03:DICT_4X4_50"),
                             every("text")),
        "write_board_png": (mvtex.write_board_png, lambda: dict(spec=board, path=sb.out("board") + ".png",
                                                                pixels_per_square=8),
                            {"spec": HOSTILE, "path": NOT_TEXT, "dpi": NOT_TEXT, "pixels_per_square": NOT_TEXT,
                             "margin_m": NOT_TEXT}),
        "fill": (mvtex.fill, lambda: dict(faces=ds.faces, positions=np.asarray(ds.rest, np.float64),
                                          values=np.zeros((n, 2)), assigned=np.arange(n) % 2 == 0),
                 every("faces", "positions", "values", "assigned", "method", "groups")),
        "load_model": (mvtex.load_model, lambda: dict(path=sb.out("model")), {"path": NOT_TEXT}),
        "load_corrector": (mvtex.load_corrector, lambda: dict(path=sb.out("geometry")), {"path": NOT_TEXT}),
        "train_geometry": (mvtex.train_geometry,
                           lambda: dict(dataset=ds, out=sb.out("geometry"), options=mvtex.GeometryOptions(components=2),
                                        progress=False),
                           {"dataset": NOT_TEXT, "out": NOT_TEXT, "options": HOSTILE}),
        "correct": (mvtex.correct, lambda: dict(dataset=ds, model=sb.out("geometry"), out=sb.out("corrected"),
                                                progress=False),
                    {"dataset": NOT_TEXT, "model": NOT_TEXT, "out": NOT_TEXT, "poses": NOT_TEXT, "options": HOSTILE}),
        "ModelConfig": (mvtex.ModelConfig.read, lambda: dict(directory=sb.out("model")), {"directory": NOT_TEXT}),
        "slide_dataset": (mvtex.slide_dataset,
                          lambda: dict(dataset=ds, rig=rig, out=sb.out("slid"), poses=[0],
                                       options=mvtex.SlideOptions(subdiv=0), progress=False),
                          {"dataset": NOT_TEXT, "rig": NOT_TEXT, "out": NOT_TEXT, "poses": NOT_TEXT, "options": HOSTILE,
                           "cameras": NOT_TEXT, "workers": NOT_TEXT, "scheduler": NOT_TEXT}),
        "evaluate": (mvtex.evaluate, lambda: dict(dataset=ds, rig=rig, texcoord_set=tc, poses=[0], progress=False),
                     {"dataset": NOT_TEXT, "rig": NOT_TEXT, "texcoord_set": NOT_TEXT, "poses": NOT_TEXT,
                      "cameras": NOT_TEXT, "heatmaps": NOT_TEXT, "workers": NOT_TEXT}),
        "triangulate_pose": (mvtex.triangulate_pose, lambda: dict(dataset=ds, rig=rig, texcoords=tc, pose=0, out=None),
                             {"dataset": NOT_TEXT, "rig": NOT_TEXT, "texcoords": NOT_TEXT, "pose": HOSTILE,
                              "out": NOT_TEXT, "options": HOSTILE}),
        "novel_views": (mvtex.novel_views,
                        lambda: dict(dataset=ds, rig=rig, texcoords=tc, out=sb.out("views"), weights=[{"a": 1.0}],
                                     names=["v"], poses=[0], progress=False),
                        {"dataset": NOT_TEXT, "rig": NOT_TEXT, "texcoords": NOT_TEXT, "out": NOT_TEXT,
                         "weights": NOT_TEXT, "names": NOT_TEXT, "poses": NOT_TEXT, "options": HOSTILE}),
        "stereo_preview": (mvtex.stereo_preview,
                           lambda: dict(dataset=ds, rig=rig, texcoords=tc, pose=0, out=sb.out("preview"),
                                        progress=False),
                           {"dataset": NOT_TEXT, "rig": NOT_TEXT, "texcoords": NOT_TEXT, "pose": HOSTILE,
                            "out": NOT_TEXT, "weights": NOT_TEXT, "options": HOSTILE}),
        "export_scene": (mvtex.export_scene,
                         lambda: dict(dataset=ds, texcoords=tc, pose=0, out=sb.out("scene"), rig=rig,
                                      options=mvtex.ExportOptions(texture_size=64, viewer=False)),
                         {"dataset": NOT_TEXT, "texcoords": NOT_TEXT, "pose": HOSTILE, "out": NOT_TEXT,
                          "rig": NOT_TEXT, "options": HOSTILE}),
        "render_pose": (mvtex.render_pose, lambda: dict(dataset=ds, rig=rig, pose=0, out=sb.out("render"),
                                                        progress=False),
                        {"dataset": NOT_TEXT, "rig": NOT_TEXT, "pose": HOSTILE, "out": NOT_TEXT,
                         "texcoord_set": NOT_TEXT}),
        "train": (mvtex.train, lambda: dict(dataset=ds, texcoords=tc, out=sb.out("model"), camera="a",
                                            options=mvtex.TrainOptions(arch="gp", epochs=1), progress=False),
                  {"dataset": NOT_TEXT, "texcoords": NOT_TEXT, "out": NOT_TEXT, "camera": NOT_TEXT,
                   "options": HOSTILE}),
        "train_cameras": (mvtex.train_cameras,
                          lambda: dict(dataset=ds, texcoords=tc, cameras=["a"], out=sb.out("models"),
                                       options=mvtex.TrainOptions(arch="gp", epochs=1), progress=False),
                          {"dataset": NOT_TEXT, "texcoords": NOT_TEXT, "cameras": NOT_TEXT, "out": NOT_TEXT,
                           "options": HOSTILE}),
        "train_models": (mvtex.train_models,
                         lambda: dict(dataset=ds, texcoords=tc, cameras=["a"], out=sb.out("models"),
                                      options=mvtex.TrainOptions(arch="gp", epochs=1), progress=False),
                         {"dataset": NOT_TEXT, "texcoords": NOT_TEXT, "cameras": NOT_TEXT, "out": NOT_TEXT,
                          "options": HOSTILE, "rig": NOT_TEXT, "workers": HOSTILE}),
        "predict": (mvtex.predict, lambda: dict(dataset=ds, models=[sb.out("nomodel")], out=sb.out("pred"), poses=[0],
                                                progress=False),
                    {"dataset": NOT_TEXT, "models": NOT_TEXT, "out": NOT_TEXT, "poses": NOT_TEXT, "rig": NOT_TEXT}),
        "run_bench": (mvtex.run_bench, lambda: dict(dataset=ds, rig=sb.out("norig") + ".yaml", poses=[0], repeats=1,
                                                    workers=1, progress=False),
                      {"dataset": NOT_TEXT, "rig": NOT_TEXT, "poses": NOT_TEXT, "subdiv": NOT_TEXT,
                       "repeats": NOT_TEXT, "workers": NOT_TEXT}),
        "run_demo": (mvtex.run_demo, lambda: dict(out=sb.out("demo"), options=mvtex.DemoOptions()),
                     {"out": NOT_TEXT, "options": HOSTILE}),
        "write_synth": (mvtex.write_synth, lambda: dict(path=sb.out("synth"), options=mvtex.SynthOptions(num_poses=4)),
                        {"path": NOT_TEXT, "options": HOSTILE}),
        "synthesize": (mvtex.synthesize, lambda: dict(options=mvtex.SynthOptions(num_poses=4)), {"options": HOSTILE}),
        "import_sequences": (mvtex.import_sequences,
                             lambda: dict(out=sb.out("imported"), gt_glob=str(sb.root / "none*.obj"),
                                          inferred_glob=str(sb.root / "none*.obj"), progress=False),
                             {"out": NOT_TEXT, "gt_glob": NOT_TEXT, "inferred_glob": NOT_TEXT, "poses_file": NOT_TEXT,
                              "name": NOT_TEXT, "body_glob": NOT_TEXT}),
        "calibrate_folder": (mvtex.calibrate_folder,
                             lambda: dict(images=sb.out("noimages"), rig_file=sb.out("rig") + ".yaml",
                                          options=mvtex.CalibrateOptions(board=board), progress=False),
                             {"images": NOT_TEXT, "rig_file": NOT_TEXT, "options": HOSTILE, "pictures": NOT_TEXT}),
        "calibrate": (mvtex.calibrate, lambda: dict(cameras=[], options=mvtex.CalibrateOptions(board=board),
                                                    progress=False),
                      {"cameras": HOSTILE, "options": HOSTILE}),
        "rasterize": (mvtex.rasterize, lambda: dict(ctx=sb.gl, positions=np.asarray(ds.gt[0], np.float64),
                                                    faces=ds.faces, camera=cam),
                      every("ctx", "positions", "faces", "camera", "occluder")),
        "render_textured": (mvtex.render_textured,
                            lambda: dict(ctx=sb.gl, positions=np.asarray(ds.gt[0], np.float64), faces=ds.faces,
                                         texcoords=ds.uv, camera=cam),
                            every("ctx", "positions", "faces", "texcoords", "camera", "normals", "body")),
        "interpolate": (mvtex.interpolate, lambda: dict(values=ds.uv, raster=sb.raster, faces=ds.faces),
                        every("values", "raster", "faces")),
        "MaterialMap": (mvtex.MaterialMap, lambda: dict(faces=ds.faces, uv=ds.uv, rest=ds.rest, resolution=64,
                                                        ctx=sb.gl),
                        every("faces", "uv", "rest", "resolution")),
        "slide_pose": (mvtex.slide_pose,
                       lambda: dict(gt_positions=np.asarray(ds.gt[0], np.float64),
                                    inferred_positions=np.asarray(ds.inferred[0], np.float64), faces=ds.faces,
                                    uv=ds.uv, camera=cam, subdivision=sb.subdivision,
                                    options=mvtex.SlideOptions(subdiv=0), ctx=sb.gl),
                       every("gt_positions", "inferred_positions", "faces", "uv", "camera", "subdivision", "options",
                             "topology", "body")),
        "reconstruct": (mvtex.reconstruct,
                        lambda: dict(gt_uv=ds.uv, inferred_positions=tc.positions(np.asarray(ds.inferred[0], np.float64)),
                                     faces=tc.faces, uv=tc.uv, texcoords={c: tc.texcoords(c, 0) for c in tc.cameras},
                                     rig=rig, gt_faces=ds.faces, ctx=sb.gl),
                        every("gt_uv", "inferred_positions", "faces", "uv", "texcoords", "rig", "options", "gt_faces",
                              "assigned", "rest", "body")),
        "rasterize_uv": (mvtex.rasterize_uv, lambda: dict(ctx=sb.gl, uv=ds.uv, faces=ds.faces, width=32, height=32),
                         every("ctx", "uv", "faces", "width", "height")),
    }


OPTIONS = {
    "SynthOptions": ("num_poses", "seed", "pca_components", "ridge", "garment", "body"),
    "SlideOptions": ("subdiv", "fill", "max_displacement", "depth_tolerance", "break_ratio", "radius", "cross_chart"),
    "ReconOptions": ("max_reprojection_px", "max_surface_distance", "max_stretch", "consensus_px",
                     "consensus_scale", "fill_shape", "smooth", "smooth_iterations", "uv_resolution",
                     "depth_tolerance", "require_assigned", "max_combinations", "refine_iterations",
                     "error_scale_m", "strain_scale", "engine", "use_prior", "prior_gate", "prior_fill"),
    "ViewOptions": ("method", "uv_resolution"),
    "PreviewOptions": ("ipd", "method", "path", "frames_per_segment", "margin"),
    "ExportOptions": ("texture_size", "viewer"),
    "TrainOptions": ("arch", "components", "widths", "epochs", "resolution", "batch_size", "lr", "device", "seed",
                     "patience", "weight_assigned"),
    "GeometryOptions": ("components", "iterations", "device"),
    "CorrectOptions": ("shrink",),
    "DemoOptions": ("num_poses", "seed", "tsnn"),
    "BoardSpec": ("cols", "rows", "square_m", "marker_m", "dictionary"),
    "CalibrateOptions": ("board", "reference", "min_corners", "distortion", "huber_px"),
}
OPTION_BASE = {"BoardSpec": dict(cols=5, rows=4, square_m=0.04, marker_m=0.03, dictionary="DICT_4X4_50")}


def typed_or_nothing(call) -> None:
    """Run `call`; only a typed mvtex error may come out."""
    try:
        call()
    except mvtex.InputError as err:
        assert str(err).strip() and "\n" not in str(err), repr(err)


@pytest.fixture
def sandbox(tmp_path, tiny_dataset, front_rig, slid_sheet, gl, monkeypatch):
    monkeypatch.chdir(tmp_path)  # a hostile path that is valid text stays in here
    sb = Sandbox(tmp_path, tiny_dataset, front_rig, slid_sheet)
    sb.gl = gl
    from mvtex.data.mesh import subdivide

    ds = sb.dataset
    sb.raster = mvtex.rasterize(gl, np.asarray(ds.gt[0], np.float64), ds.faces, front_rig.cameras[0])
    sb.subdivision = subdivide(ds.faces, ds.num_vertices, 0)
    return sb


NAMES = ["Camera", "look_at", "Rig", "load_rig", "save_rig", "load_dataset", "save_dataset", "open_texcoords",
         "save_texcoords", "project_points", "triangulate_points", "interpolate_camera", "parse_board_spec",
         "write_board_png", "fill", "load_model", "ModelConfig", "slide_dataset", "evaluate", "triangulate_pose",
         "novel_views", "stereo_preview", "export_scene", "render_pose", "train", "train_cameras", "train_models",
         "predict", "run_bench", "run_demo", "train_geometry", "correct", "load_corrector",
         "write_synth", "synthesize", "import_sequences", "calibrate_folder", "calibrate", "rasterize",
         "render_textured", "rasterize_uv", "interpolate", "MaterialMap", "slide_pose", "reconstruct"]


@pytest.mark.slow
@pytest.mark.parametrize("name", NAMES)
def test_a_function_given_a_hostile_argument_raises_a_typed_error(name, sandbox):
    function, base, fuzzed = targets(sandbox)[name]

    @FUZZ
    @given(data=st.data())
    def check(data):
        argument = data.draw(st.sampled_from(sorted(fuzzed)), label="argument")
        value = data.draw(fuzzed[argument], label="value")
        kwargs = base()
        kwargs[argument] = value
        typed_or_nothing(lambda: function(**kwargs))

    check()


@pytest.mark.parametrize("name", sorted(OPTIONS))
def test_an_options_field_of_a_hostile_type_raises_a_typed_error(name, sandbox):
    cls = getattr(mvtex, name)
    base = dict(OPTION_BASE.get(name, {}))
    if name == "CalibrateOptions":
        base["board"] = mvtex.parse_board_spec("charuco:5x4:0.04:0.03:DICT_4X4_50")

    @FUZZ
    @given(data=st.data())
    def check(data):
        field = data.draw(st.sampled_from(OPTIONS[name]), label="field")
        value = data.draw(HOSTILE, label="value")
        typed_or_nothing(lambda: cls(**{**base, field: value}))

    check()


def test_the_fuzzed_names_are_the_public_api():
    """Every public function and options class is fuzzed (the result types are not)."""
    results = {"InputError", "OptionError", "OutputError", "NoGroundTruthError", "Dataset", "TexcoordSet", "SynthResult", "GLContext", "Raster",
               "Evaluation", "Reconstruction", "ReconReport", "TrainResult", "TrainedCameras", "GeometryResult",
               "CorrectResult", "__version__"}
    assert set(mvtex.__all__) - results - set(NAMES) - set(OPTIONS) == set()
