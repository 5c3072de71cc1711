"""Every loader fuzzed through the command line: damaged dataset files, rig YAML, texcoord
sets, OBJ/PLY imports, model directories and option values. Whatever the damage, `main`
returns 0 (the damage was harmless) or 2 with one line naming the file or option; it never
raises, never leaves temporaries or half-written outputs, and writes nothing outside --out."""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mvtex.cli import main

FUZZ = settings(max_examples=25, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

# Damage to a file's bytes: cut it, flip one bit, empty it, or append garbage.
damage = st.one_of(
    st.tuples(st.just("truncate"), st.floats(0, 1)),
    st.tuples(st.just("flip"), st.floats(0, 1), st.integers(0, 7)),
    st.tuples(st.just("empty")),
    st.tuples(st.just("append"), st.binary(min_size=1, max_size=64)),
)

hostile_text = st.sampled_from(["../../x", "/etc/x", "a/b", ".", "..", "mesh.npz", "", " ", "a" * 100, "\x00",
                                "NaN", "-1", "1e400", "abc", "[1, 2]", "{}", "null", "true"])

number_text = st.one_of(
    st.integers(-10**12, 10**12).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["nan", "inf", "-inf", "1e400", "0", "-0", "0x10", "", "abc", "1,2", " 3 "]),
)


def damage_file(path: Path, how: tuple) -> None:
    data = path.read_bytes()
    if how[0] == "truncate":
        data = data[: int(how[1] * len(data))]
    elif how[0] == "flip" and data:
        i = min(len(data) - 1, int(how[1] * len(data)))
        data = data[:i] + bytes([data[i] ^ (1 << how[2])]) + data[i + 1:]
    elif how[0] == "empty":
        data = b""
    elif how[0] == "append":
        data = data + how[1]
    path.write_bytes(data)


def snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def check(argv: list, root: Path, out: Path | None, inputs: dict[str, bytes]) -> int:
    """Run main(argv) in the sandbox `root`; assert the guarantees; return the exit code."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main([str(a) for a in argv])  # an exception here is a traceback for the user
    err = err.getvalue()
    assert code in (0, 2), err
    if code == 2:
        lines = [line for line in err.strip().splitlines() if line.startswith("mvtex ")]
        assert len(lines) == 1 and "Traceback" not in err, err
        assert out is None or not out.exists() or not any(out.iterdir()), "half-written output"
    after = snapshot(root)
    # Inputs untouched; everything new lies under --out; no temporaries, aside copies or locks.
    for name, data in inputs.items():
        assert after.get(name) == data, f"{name} changed"
    new = [name for name in after if name not in inputs]
    prefix = None if out is None else str(out.relative_to(root))
    assert all(prefix is not None and (name == prefix or name.startswith(prefix + "/")) for name in new), new
    hidden = [p.name for p in root.iterdir() if p.name.startswith(".")]
    assert not hidden and not list(root.glob("*.partial")), hidden
    return code


@contextlib.contextmanager
def sandbox(*sources: Path):
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for src in sources:
            if src.is_dir():
                shutil.copytree(src, root / src.name)
            else:
                shutil.copy(src, root / src.name)
        yield root


@pytest.mark.gl
@FUZZ
@given(name=st.sampled_from(["mesh.npz", "gt.npy", "inferred.npy", "poses.npy", "dataset.json", "split.json"]),
       how=damage)
@pytest.mark.slow
def test_damaged_dataset_files(tiny_dataset, rig_file, gl, name, how):
    with sandbox(tiny_dataset, rig_file) as root:
        damage_file(root / "sheet" / name, how)
        inputs = snapshot(root)
        check(["render", root / "sheet", "--rig", root / "rig.yaml", "--pose", 1, "--cameras", "a",
               "--out", root / "out", "--quiet"], root, root / "out", inputs)


@pytest.mark.gl
@FUZZ
@given(field=st.sampled_from(["name", "width", "height", "format", "version"]), value=st.one_of(hostile_text, number_text),
       cut=st.one_of(st.none(), st.floats(0, 1)))
@pytest.mark.slow
def test_damaged_rig_yaml(tiny_dataset, rig_file, gl, field, value, cut):
    with sandbox(tiny_dataset, rig_file) as root:
        lines = (root / "rig.yaml").read_text().splitlines()
        i = next(i for i, line in enumerate(lines) if line.strip().startswith(f"{field}:"))
        lines[i] = lines[i].split(":")[0] + ": " + json.dumps(value)
        text = "\n".join(lines) + "\n"
        if cut is not None:
            text = text[: int(cut * len(text))]
        (root / "rig.yaml").write_text(text)
        inputs = snapshot(root)
        check(["render", root / "sheet", "--rig", root / "rig.yaml", "--pose", 1, "--out", root / "out", "--quiet"],
              root, root / "out", inputs)


json_value = st.recursive(st.one_of(st.none(), st.booleans(), st.integers(-10**20, 10**20),
                                    st.floats(allow_nan=False), hostile_text),
                          lambda inner: st.lists(inner, max_size=3), max_leaves=6)


@pytest.mark.gl
@FUZZ
@given(key=st.sampled_from(["poses", "cameras", "subdiv", "format", "version"]), value=json_value,
       array=st.sampled_from([None, "nan", "inf", "huge", "float64", "int32", "shape", "truncate"]))
@pytest.mark.slow
def test_damaged_texcoord_sets(tiny_dataset, rig_file, slid_sheet0, gl, key, value, array):
    with sandbox(tiny_dataset, rig_file, slid_sheet0) as root:
        tc = root / "tc"
        meta = json.loads((tc / "texcoords.json").read_text())
        meta[key] = value
        (tc / "texcoords.json").write_text(json.dumps(meta))
        file = tc / "a" / "displacement.npy"
        d = np.load(file)
        if array == "truncate":
            damage_file(file, ("truncate", 0.5))
        elif array is not None:
            d = {"nan": lambda: np.where(d == d.max(), np.nan, d), "inf": lambda: np.where(d == d.max(), np.inf, d),
                 "huge": lambda: d * 1e30, "float64": lambda: d.astype(np.float64),
                 "int32": lambda: d.astype(np.int32), "shape": lambda: d[:, :-1]}[array]()
            np.save(file, d)
        inputs = snapshot(root)
        check(["eval", root / "sheet", "--rig", root / "rig.yaml", "--texcoords", tc, "--poses", "0", "--json",
               "--quiet"], root, None, inputs)


@FUZZ
@given(which=st.sampled_from(["g0.obj", "g1.obj", "i1.obj"]), how=damage,
       line=st.one_of(st.none(), st.tuples(st.floats(0, 1), st.sampled_from(
           ["v nan 0 0", "v 1e400 0 0", "vt x y", "f 1 2 999999", "f -5 -6 -7", "v 1 2", "f 1/1", "o ../x"]))))
@pytest.mark.slow
def test_damaged_obj_imports(which, how, line):
    from helpers import grid_mesh, wave, write_obj

    with sandbox() as root:
        faces, uv, rest = grid_mesh(4, 4)
        for k in range(2):
            write_obj(root / f"g{k}.obj", wave(rest, 0.01, k), uv, faces)
            write_obj(root / f"i{k}.obj", wave(rest, 0.003, k), uv, faces)
        if line is not None:
            lines = (root / which).read_text().splitlines()
            lines.insert(int(line[0] * len(lines)), line[1])
            (root / which).write_text("\n".join(lines) + "\n")
        damage_file(root / which, how)
        inputs = snapshot(root)
        code = check(["import", "--out", root / "ds", "--gt", root / "g*.obj", "--inferred", root / "i*.obj", "--quiet"],
                     root, root / "ds", inputs)
        if code == 0:
            from mvtex.data.dataset import load_dataset

            assert np.isfinite(np.asarray(load_dataset(root / "ds").gt)).all()


@FUZZ
@given(path=st.sampled_from([("camera",), ("mesh", "subdiv"), ("mesh", "num_vertices"), ("architecture", "resolution"),
                             ("architecture", "width"), ("architecture", "pose_dim"), ("architecture", "depth"),
                             ("format",), ("architecture",)]),
       value=json_value, weights=st.one_of(st.none(), damage))
@pytest.mark.slow
def test_damaged_model_directories(tiny_dataset, path, value, weights):
    pytest.importorskip("torch")
    from helpers import fake_model

    with sandbox(tiny_dataset) as root:
        model = fake_model(root / "m", root / "sheet")
        config = json.loads((model / "config.json").read_text())
        target = config
        for key in path[:-1]:
            target = target[key]
        target[path[-1]] = value
        (model / "config.json").write_text(json.dumps(config))
        if weights is not None:
            damage_file(model / "model.safetensors", weights)
        inputs = snapshot(root)
        check(["predict", root / "sheet", "--model", model, "--out", root / "out", "--poses", "0:2", "--quiet"],
              root, root / "out", inputs)


@FUZZ
@given(option=st.sampled_from([("triangulate", "--max-reprojection-px"), ("triangulate", "--max-surface-distance"),
                               ("triangulate", "--pose"), ("slide", "--max-displacement"), ("slide", "--workers"),
                               ("slide", "--poses"), ("slide", "--subdiv"), ("train", "--epochs"),
                               ("train", "--resolution"), ("train", "--device"), ("train", "--cameras"),
                               ("train", "--workers"), ("eval", "--workers"), ("eval", "--poses"),
                               ("views", "--workers"), ("synth", "--num-poses")]),
       value=st.one_of(number_text, hostile_text))
@pytest.mark.slow
def test_option_values(tiny_dataset, rig_file, slid_sheet0, option, value):
    """Every option value is either refused in one line or accepted; the run then stops at
    a foreign --out (so a valid value costs nothing)."""
    command, flag = option
    with sandbox(tiny_dataset, rig_file, slid_sheet0) as root:
        out = root / "mine"
        out.mkdir()
        (out / "keep.txt").write_text("x")
        base = {"triangulate": ["--rig", root / "rig.yaml", "--texcoords", root / "tc", "--pose", "0"],
                "slide": ["--rig", root / "rig.yaml"], "train": ["--texcoords", root / "tc", "--cameras", "a"],
                "eval": ["--rig", root / "rig.yaml", "--texcoords", root / "tc", "--heatmaps", out / "h"],
                "views": ["--rig", root / "rig.yaml", "--texcoords", root / "tc", "--between", "a,b", "--steps", "2"],
                "synth": []}[command]
        target = ["--out", out] if command == "synth" else [root / "sheet"]
        tail = [] if command in ("eval", "synth") else ["--out", out]
        inputs = snapshot(root)
        argv = [command, *target, *base, *tail, f"{flag}={value}"]
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            code = main([str(a) for a in argv])
        if command == "eval" and code == 0:
            return  # a valid eval: heatmaps under the given folder, checked elsewhere
        assert code == 2, err.getvalue()
        lines = [line for line in err.getvalue().strip().splitlines() if line.startswith("mvtex ")]
        assert len(lines) == 1 and "Traceback" not in err.getvalue(), err.getvalue()
        assert snapshot(root) == inputs


# -- the newer commands' inputs -------------------------------------------------------------

board_spec = st.one_of(
    st.builds(lambda c, r, s, m, d: f"charuco:{c}x{r}:{s}:{m}:{d}", st.integers(-2, 40), st.integers(-2, 40),
              number_text, number_text, st.sampled_from(["DICT_4X4_50", "DICT_5X5_100", "DICT_X", "dict_4x4_50", ""])),
    hostile_text, st.text(max_size=40))


@FUZZ
@given(spec=board_spec, dpi=st.one_of(st.none(), number_text), pps=st.one_of(st.none(), number_text))
def test_board_specs_and_sizes(spec, dpi, pps):
    with sandbox() as root:
        out = root / "board.png"
        argv = ["board", spec, "--out", out, "--json"]
        argv += ["--dpi", dpi] if dpi is not None else []
        argv += [f"--pixels-per-square={pps}"] if pps is not None and dpi is None else []
        check(argv, root, out, {})


weights_text = st.one_of(
    st.dictionaries(st.sampled_from(["a", "b", "c", "", "a=b", " a"]), number_text, max_size=3).map(
        lambda d: ",".join(f"{k}={v}" for k, v in d.items())),
    hostile_text, st.text(max_size=30))


@pytest.mark.gl
@FUZZ
@given(how=st.one_of(st.tuples(st.just("--weights"), weights_text),
                     st.tuples(st.just("--between"), st.sampled_from(["a,b", "a,a", "b,a", "a", "a,b,c", ""]),
                               number_text),
                     st.tuples(st.just("--grid"), st.sampled_from(["a,b,a,b", "a,b", "a,b,c,d", ""]), number_text)))
@pytest.mark.slow
def test_view_weights_and_steps(tiny_dataset, rig_file, slid_sheet0, how):
    with sandbox(tiny_dataset, rig_file, slid_sheet0) as root:
        out = root / "v"
        flags = [how[0], how[1]] if how[0] == "--weights" else [how[0], how[1], f"--steps={how[2]}"]
        check(["views", root / "sheet", "--rig", root / "rig.yaml", "--texcoords", root / "tc", "--out", out,
               "--method", "blend", "--poses", "0", *flags, "--quiet"], root, out, snapshot(root))


@FUZZ
@given(names=st.lists(st.one_of(hostile_text, st.sampled_from(["cam0", "CAM0", "cam 1", "kamera_ü", "c" * 70])),
                      min_size=1, max_size=3), image=st.sampled_from([b"", b"not an image", None]))
@pytest.mark.slow
def test_calibration_image_folders(names, image):
    import cv2

    with sandbox() as root:
        images = root / "images"
        for name in names:
            try:
                (images / name).mkdir(parents=True, exist_ok=True)
            except (OSError, ValueError):
                continue  # a name no file system takes
            if image is None:
                cv2.imwrite(str(images / name / "f0.png"), np.full((60, 80), 128, np.uint8))
            else:
                (images / name / "f0.png").write_bytes(image)
        out = root / "out"
        check(["calibrate", images, "--board", "charuco:5x4:0.04:0.03:DICT_4X4_50", "--out", out / "rig.yaml",
               "--quiet"], root, out, snapshot(root))


@FUZZ
@given(which=st.sampled_from(["cameras.txt", "images.txt", "frames.txt", "rigs.txt"]), how=damage,
       line=st.integers(0, 8), field=st.integers(0, 12), value=st.one_of(number_text, hostile_text))
@pytest.mark.slow
def test_damaged_colmap_text_models(which, how, line, field, value):
    with sandbox() as root:
        assert main(["rig", "square4", "--to-colmap", str(root / "model"), "--text"]) == 0
        path = root / "model" / which
        lines = path.read_text().splitlines()
        data = [i for i, text in enumerate(lines) if text and not text.startswith("#")]
        if data:
            i = data[line % len(data)]
            fields = lines[i].split()
            fields[field % len(fields)] = value
            lines[i] = " ".join(fields)
            path.write_text("\n".join(lines) + "\n")
        damage_file(path, how)
        out = root / "out"
        check(["rig", "--from-colmap", root / "model", "--out", out / "rig.yaml", "--json"], root, out,
              snapshot(root))


# -- the file-system states of a shared folder ------------------------------------------------------

@pytest.fixture(scope="module")
def binds(tmp_path_factory) -> bool:
    from fs_states import bind_mounts_allowed

    return bind_mounts_allowed(tmp_path_factory.mktemp("bind-probe"))


def _fs_state_strategy():
    from fs_states import state

    return state


@pytest.mark.slow
@FUZZ
@given(fs=_fs_state_strategy(), command=st.sampled_from(["to-colmap", "board"]))
def test_writers_in_hostile_file_system_states(binds, fs, command):
    """Links at the lock's, the manifest's and the stamps' names, a user's files named like
    them, links and bind mounts inside the output (where the machine allows them): exit 0 or
    2 with one line, and nothing planted (or pointed to) changes or goes away."""
    from fs_states import plant

    with sandbox() as root:
        (root / "work").mkdir()
        out = root / "work" / ("model" if command == "to-colmap" else "board.png")
        argv = ["rig", "stereo", "--to-colmap", out] if command == "to-colmap" else \
            ["board", "charuco:5x4:0.04:0.03:DICT_4X4_50", "--out", out, "--pixels-per-square", "20"]
        if fs["out"] == "written":
            assert main([str(a) for a in argv]) == 0
        elif fs["out"] == "empty" and command == "to-colmap":
            out.mkdir()
        planted = plant(root, out, fs["plantings"], binds=binds)
        try:
            err = io.StringIO()
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                code = main([str(a) for a in argv] + (["--overwrite"] if fs["overwrite"] else []))
            assert code in (0, 2), err.getvalue()
            if code == 2:
                lines = err.getvalue().strip().splitlines()
                assert len(lines) == 1 and lines[0].startswith(f"mvtex {argv[0]}: error: "), lines
            planted.check()
        finally:
            planted.unmount()
