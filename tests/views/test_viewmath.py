"""The viewer's mathematics (mvtex/web/viewmath.js, run in node) against the Python it copies:
the eye's weights (`weights_for_centre`), the novel camera of view weights
(`interpolate_camera`), the eyes of a stereo pair (`eye_cameras`), and the projection of an
OpenCV camera in three.js against `cv2.projectPoints`. Skipped where node is missing."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from browser import NODE

from mvtex.data.camera import look_at
from mvtex.data.rig import Rig, load_rig
from mvtex.views.cameras import interpolate_camera, weights_for_centre
from mvtex.views.preview import eye_cameras

VIEWMATH = Path(__file__).resolve().parents[2] / "mvtex" / "web" / "viewmath.js"
pytestmark = pytest.mark.skipif(NODE is None, reason="node is not installed")


def node(code: str, data) -> object:
    """Run `code` in node with `m` the viewmath module and `data` the JSON input; returns the
    JSON value the code prints."""
    script = f"const m = require({json.dumps(str(VIEWMATH))});\n" \
             f"const data = JSON.parse(require('fs').readFileSync(0, 'utf8'));\n{code}"
    out = subprocess.run([NODE, "-e", script], input=json.dumps(data), capture_output=True, text=True, check=False, timeout=60)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def camera_json(cam) -> dict:
    return {"width": cam.width, "height": cam.height, "K": cam.K.tolist(), "R": cam.R.tolist(), "t": cam.t.tolist()}


def odd_rig() -> Rig:
    """Seven cameras scattered on a bumpy arc, not a grid: no symmetry to lean on."""
    rng = np.random.default_rng(5)
    cams = []
    for i in range(7):
        a = np.radians(-50 + 100 * i / 6 + rng.uniform(-5, 5))
        centre = (2.0 * np.sin(a), rng.uniform(-0.7, 0.7), 2.0 * np.cos(a) + rng.uniform(-0.2, 0.2))
        cams.append(look_at(f"c{i}", centre, (0, 0.1, 0), width=320, height=240, focal=rng.uniform(380, 420)))
    return Rig(tuple(cams))


RIGS = {"stereo": lambda: load_rig("stereo"), "square4": lambda: load_rig("square4"),
        "trapezoid12": lambda: load_rig("trapezoid12"), "odd7": odd_rig}


@pytest.mark.parametrize("name", sorted(RIGS))
def test_the_eyes_weights_are_pythons(name):
    rig = RIGS[name]()
    C = np.stack([c.center for c in rig])
    rng = np.random.default_rng(1)
    lo, hi = C.min(axis=0) - 0.6, C.max(axis=0) + 0.6
    eyes = np.vstack([rng.uniform(lo, hi, (40, 3)), C, (C[0] + C[-1]) / 2])  # around, at, and between cameras
    got = np.array(node("console.log(JSON.stringify(data.eyes.map(e => m.weightsForCentre(data.C, e))))",
                        {"C": C.tolist(), "eyes": eyes.tolist()}))
    want = np.array([list(weights_for_centre(rig, rig.names, e).values()) for e in eyes])
    assert np.abs(got - want).max() < 1e-7
    # At a camera's own viewpoint, weight 1 on it, exactly (its sliding exactly).
    assert np.array_equal(got[len(eyes) - len(C) - 1:-1], np.eye(len(C)))


def test_the_weights_rule():
    """Weights reproduce the eye where a blend can, stay on the nearest cameras, are even
    where the cameras are (the centre of a square), and are the linear weights of two."""
    square = load_rig("square4")
    centre = np.mean([c.center for c in square], axis=0)
    assert weights_for_centre(square, square.names, centre) == pytest.approx(dict.fromkeys(square.names, 0.25))
    mid = (square["tl"].center + square["tr"].center) / 2
    assert weights_for_centre(square, square.names, mid) == pytest.approx({"tl": 0.5, "tr": 0.5, "bl": 0, "br": 0})
    # Near a corner of the square: only the corner and its two neighbours.
    near_tl = 0.8 * square["tl"].center + 0.1 * square["tr"].center + 0.1 * square["bl"].center
    w = weights_for_centre(square, square.names, near_tl)
    assert w["br"] == pytest.approx(0.0, abs=1e-9) and sum(w.values()) == pytest.approx(1.0)
    assert np.allclose(sum(w[n] * square[n].center for n in square.names), near_tl, atol=1e-6)
    # Off the array's surface, the blend is the nearest point a blend reaches.
    stereo = load_rig("stereo")
    off = 0.3 * stereo["left"].center + 0.7 * stereo["right"].center + np.array([0.0, 0.4, 0.3])
    assert weights_for_centre(stereo, stereo.names, off) == pytest.approx({"left": 0.3, "right": 0.7})
    trap = load_rig("trapezoid12")
    for name in trap.names:
        assert weights_for_centre(trap, trap.names, trap[name].center)[name] == 1.0


@pytest.mark.parametrize("weights", [{"tl": 0.5, "tr": 0.5}, {"tl": 0.2, "br": 0.8},
                                     {"tl": 0.1, "tr": 0.2, "bl": 0.3, "br": 0.4}, {"tr": 1.0},
                                     {"tl": 0.25, "tr": 0.25, "bl": 0.25, "br": 0.25}])
def test_the_novel_camera_is_pythons(weights):
    rig = load_rig("square4")
    got = node("console.log(JSON.stringify(m.interpolateCamera(data.cams, data.w)))",
               {"cams": {c.name: camera_json(c) for c in rig}, "w": weights})
    want = interpolate_camera(rig, weights, "v")
    for key in ("K", "R", "t"):
        assert np.abs(np.array(got[key]) - getattr(want, key)).max() < 1e-12, key
    assert (got["width"], got["height"]) == (want.width, want.height)


def test_the_novel_camera_of_many_is_pythons():
    rig = odd_rig()
    w = dict(zip(rig.names, np.random.default_rng(2).dirichlet(np.ones(len(rig.names))).tolist()))
    w[rig.names[0]] += 1.0 - sum(w.values())
    got = node("console.log(JSON.stringify(m.interpolateCamera(data.cams, data.w)))",
               {"cams": {c.name: camera_json(c) for c in rig}, "w": w})
    want = interpolate_camera(rig, w, "v")
    for key in ("K", "R", "t"):
        assert np.abs(np.array(got[key]) - getattr(want, key)).max() < 1e-9, key


def test_the_stereo_eyes_are_previews():
    viewpoint = interpolate_camera(load_rig("stereo"), {"left": 0.3, "right": 0.7}, "viewpoint")
    got = node("console.log(JSON.stringify(m.eyeCameras(data.cam, 0.064)))", {"cam": camera_json(viewpoint)})
    for g, want in zip(got, eye_cameras(viewpoint, 0.064)):
        assert np.abs(np.array(g["t"]) - want.t).max() < 1e-12 and np.array_equal(np.array(g["R"]), want.R)


def test_the_three_js_camera_projects_as_opencv():
    """The GL projection and pose the viewer gives three.js put points on the canvas where
    cv2.projectPoints puts them (OpenCV pixel centres; canvas rows top-down)."""
    import cv2

    cam = look_at("c", (0.4, -0.3, 1.9), (0.02, 0.05, 0.0), width=640, height=480, focal=700.0)
    K = cam.K.copy()
    K[0, 2], K[1, 2], K[0, 0] = 301.7, 255.2, 712.0  # off-centre, non-square pixels
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.3, 0.3, (60, 3))
    code = """
    const P = m.projectionFromK(data.K, 640, 480, 0.1, 10), V = m.worldFromGLCamera(data.R, data.t);
    const Vinv = (() => { const R = [0, 1, 2].map(i => [0, 1, 2].map(j => V[j][i]));
      const c = [V[0][3], V[1][3], V[2][3]]; const t = m.matVec(R, c).map(x => -x);
      return [[...R[0], t[0]], [...R[1], t[1]], [...R[2], t[2]], [0, 0, 0, 1]]; })();
    const out = data.points.map(p => { const clip = m.matVec(m.matMul(P, Vinv), [...p, 1]);
      const ndc = [clip[0] / clip[3], clip[1] / clip[3]];
      return [(ndc[0] + 1) / 2 * 640 - 0.5, (1 - ndc[1]) / 2 * 480 - 0.5]; });
    console.log(JSON.stringify({out, back: m.openCVFromWorldGL(V), rod: m.matrixToRodrigues(data.R),
      parsed: m.parseCamera(m.formatCamera({width: 640, height: 480, K: data.K, R: data.R, t: data.t}))}));
    """
    got = node(code, {"K": K.tolist(), "R": cam.R.tolist(), "t": cam.t.tolist(), "points": points.tolist()})
    want, _ = cv2.projectPoints(points, cv2.Rodrigues(cam.R)[0], cam.t, K, np.zeros(5))
    assert np.abs(np.array(got["out"]) - want.reshape(-1, 2)).max() < 1e-6
    assert np.abs(np.array(got["back"]["R"]) - cam.R).max() < 1e-12
    assert np.abs(np.array(got["back"]["t"]) - cam.t).max() < 1e-12
    assert np.abs(np.array(got["rod"]) - cv2.Rodrigues(cam.R)[0].ravel()).max() < 1e-9
    assert np.abs(np.array(got["parsed"]["R"]) - cam.R).max() < 1e-8  # the URL's 10 digits
    assert np.abs(np.array(got["parsed"]["K"]) - K).max() < 1e-6


def test_the_view_parameter_is_checked_as_weights_are():
    names = ["left", "right"]
    ok = node("console.log(JSON.stringify([m.parseView('left', data), m.parseView('left=0.25, right=0.75', data)]))",
              names)
    assert ok == [{"left": 1}, {"left": 0.25, "right": 0.75}]
    for bad, why in (("left=0.5", "sum to 1"), ("up=1", "no camera"), ("left=-1,right=2", ">= 0"), ("left=x", "NAME")):
        err = node(f"try {{ m.parseView({json.dumps(bad)}, data); console.log('null'); }} "
                   "catch (e) { console.log(JSON.stringify(e.message)); }", names)
        assert err is not None and why in err, (bad, err)
