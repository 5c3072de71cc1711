"""`mvtex preview`: a stereo pair of the texture-corrected cloth for an AR/VR viewer
(DESIGN §7), with numbers that say whether it looks like the real cloth.

A viewpoint inside the array's span is given by weights over array cameras (default: equal
weights over the rig's cameras that the texcoord set has); it is the novel camera of
`mvtex.views.cameras.interpolate_camera`. The two eyes sit at its centre ± ipd/2 along its x axis
(image right), with its orientation and intrinsics. Each eye's texcoords are computed like
`mvtex views` computes a view: "reconstruct" slides from the eye camera itself; "blend"
uses the weights whose blended centre is nearest the eye (`views.weights_for_centre`).

Per eye three renders (`raster.render_textured`, the fabric texture): the gt cloth with
T_G, the inferred cloth with T_G ("inferred": what the predictor alone gives) and the
(subdivided) inferred cloth with the eye's texcoords ("texcoords"). SSIM and PSNR
(scikit-image) of each inferred render against the gt render are computed over the
garment's bounding box (the pixels that differ from the background in any of the three
renders, grown by 4 px): the constant background would otherwise inflate both. An inference
set (no gt) has no gt render: its preview skips the scores (null in preview.json) and the
gt row of comparison.png.

Output (OUT, written atomically as a whole):
    stereo.png       left eye | right eye, the inferred cloth with the eyes' texcoords
    anaglyph.png     red-cyan: red from the left eye, green and blue from the right, converged
                     at the garment (each eye's picture shifted by half the disparity of the
                     cloth's centre, so that the garment sits at the screen's depth)
    comparison.png   rows gt / inferred (T_G) / texcoords, columns left / right
    preview.json     {"pose", "eyes": {"left": {"ssim": {"inferred", "texcoords"},
                      "psnr": {...}}, "right": {...}}, "viewpoint", "ipd", "method",
                      "convergence": {"depth_m", "shift_px"}, ...}
    path.gif         with `path`: the viewpoint moving through the array's cameras
"""

from __future__ import annotations

import os
import sys
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Mapping

import numpy as np
from tqdm import tqdm

from mvtex.data.camera import Camera
from mvtex.data.dataset import as_dataset
from mvtex.data.rig import Rig, as_rig, check_outside_body
from mvtex.data.texcoords import as_texcoords
from mvtex.render.pictures import grid_image, label, side_by_side
from mvtex.render.raster import rasterize
from mvtex.render.shading import render_textured
from mvtex.util.checks import as_index, as_path, check_instance
from mvtex.util.errors import InputError, OptionError
from mvtex.util.files import save_png, write_json
from mvtex.util.output import atomic_path, writer
from mvtex.views.cameras import check_weights, interpolate_camera, weights_for_centre
from mvtex.views.options import PreviewOptions
from mvtex.views.synthesizer import ViewOptions, ViewSynthesizer

BACKGROUND = (40, 40, 46)


@dataclass(frozen=True)
class EyeScores:
    """One eye's scores against the gt render: (inferred with T_G, texcoords) each.

    Attributes:
        ssim, psnr: (inferred, texcoords) SSIM and PSNR (dB; 99 for identical images); None
            for a dataset without gt (nothing to score against).
        weights: the array cameras' weights of the eye's texcoords.
        box: (row0, row1, col0, col1) of the pixels scored (the garment's bounding box).
    """

    ssim: tuple[float, float] | None
    psnr: tuple[float, float] | None
    weights: dict[str, float]
    box: tuple[int, int, int, int]

    def to_json(self) -> dict:
        def pair(p):
            return None if p is None else {"inferred": p[0], "texcoords": p[1]}

        return {"ssim": pair(self.ssim), "psnr": pair(self.psnr), "weights": self.weights, "box": list(self.box)}


@dataclass(frozen=True)
class Preview:
    """What `stereo_preview` measured and wrote (preview.json is `to_json()`)."""

    pose: int
    eyes: dict[str, EyeScores]
    viewpoint: dict
    method: str
    source: str
    texcoords: str
    options: PreviewOptions
    files: list[str]
    convergence: dict | None = None
    ground_truth: bool = True

    def to_json(self) -> dict:
        over = "garment bounding box (non-background pixels of gt/inferred/texcoords renders + margin)" \
            if self.ground_truth else None
        return {"pose": self.pose, "eyes": {k: v.to_json() for k, v in self.eyes.items()}, "viewpoint": self.viewpoint,
                "ipd": self.options.ipd, "method": self.method, "source": self.source, "texcoords": self.texcoords,
                "convergence": self.convergence, "ground_truth": self.ground_truth, "scores_over": over,
                "options": asdict(self.options), "files": self.files}


def eye_cameras(viewpoint: Camera, ipd: float) -> tuple[Camera, Camera]:
    """The left and right eyes: the viewpoint moved by ∓ipd/2 along its x axis (image right)."""

    x_axis = viewpoint.R[0]  # camera x in world coordinates
    eyes = []
    for name, sign in (("left", -1.0), ("right", 1.0)):
        centre = viewpoint.center + sign * 0.5 * ipd * x_axis
        eyes.append(replace(viewpoint, name=name, t=-viewpoint.R @ centre))
    return eyes[0], eyes[1]


def _render(ctx, positions: np.ndarray, faces: np.ndarray, texcoords: np.ndarray, camera: Camera,
            body=None) -> np.ndarray:
    """The one place this module draws: (H,W,3) uint8 textured render in GL context `ctx`
    (with the body, if given, in its matte material)."""

    return render_textured(ctx, positions, faces, texcoords, camera, background=BACKGROUND, body=body)


def garment_box(images, margin: int = 4, masks=()) -> tuple[slice, slice]:
    """Row and column slices of the bounding box of the non-background pixels of any image,
    or, given `masks` ((H,W) bool: where the cloth is, for pictures that show a body too),
    of their pixels."""
    fg = np.zeros(images[0].shape[:2], bool)
    for mask in masks:
        fg |= mask
    for im in images if not len(masks) else ():
        fg |= np.any(im != np.asarray(BACKGROUND, np.uint8), axis=2)
    if not fg.any():
        return slice(None), slice(None)
    rows, cols = np.flatnonzero(fg.any(axis=1)), np.flatnonzero(fg.any(axis=0))
    H, W = fg.shape
    return (slice(max(rows[0] - margin, 0), min(rows[-1] + margin + 1, H)),
            slice(max(cols[0] - margin, 0), min(cols[-1] + margin + 1, W)))


def image_scores(reference: np.ndarray, image: np.ndarray, box: tuple[slice, slice]) -> tuple[float, float]:
    """SSIM and PSNR (dB) of an RGB uint8 image against a reference, inside `box`
    (PSNR of identical images, infinite, is reported as 99)."""
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity  # noqa: PLC0415 (loaded on use)

    a, b = reference[box], image[box]
    ssim = structural_similarity(a, b, channel_axis=2, data_range=255)
    with np.errstate(divide="ignore"):
        psnr = peak_signal_noise_ratio(a, b, data_range=255)
    return float(ssim), float(psnr) if np.isfinite(psnr) else 99.0


def convergence(viewpoint: Camera, ipd: float, points: np.ndarray) -> dict:
    """Where the anaglyph converges: the depth (m) of the centre of `points` (the cloth) in
    the viewpoint camera, and the disparity there between the eyes, fx · ipd / depth (px):
    a point at that depth is that much further right in the left eye's picture."""
    depth = float(viewpoint.to_camera(np.asarray(points, np.float64).mean(axis=0, keepdims=True))[0, 2])
    return {"depth_m": depth, "shift_px": float(viewpoint.K[0, 0] * ipd / depth) if depth > 0 else 0.0}


def anaglyph(left: np.ndarray, right: np.ndarray, shift_px: float = 0.0) -> np.ndarray:
    """Red-cyan anaglyph (H,W,3) uint8: red from the left eye, green and blue from the right,
    the left picture moved left and the right one right by `shift_px` / 2 each (the
    convergence: what was `shift_px` apart coincides); uncovered columns are the background."""
    import cv2  # noqa: PLC0415 (loaded on use)

    def moved(image: np.ndarray, dx: float) -> np.ndarray:
        if dx == 0:
            return np.asarray(image, np.uint8)
        M = np.array([[1.0, 0.0, dx], [0.0, 1.0, 0.0]])
        h, w = image.shape[:2]
        return cv2.warpAffine(np.ascontiguousarray(image, np.uint8), M, (w, h), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=tuple(int(c) for c in BACKGROUND))

    out = np.array(moved(right, shift_px / 2), np.uint8, copy=True)
    out[..., 0] = moved(left, -shift_px / 2)[..., 0]
    return out


class _Eyes:
    """Renders both eyes of one pose; texcoords through a `views.ViewSynthesizer`."""

    def __init__(self, dataset, rig: Rig, texcoords, pose: int, method: str, array: list[str], progress: bool):

        self.dataset, self.rig, self.tc, self.pose, self.array = dataset, rig, texcoords, int(pose), array
        self.synth = ViewSynthesizer(dataset, rig, texcoords, ViewOptions(method=method))
        self.state = self.synth.prepare(pose, progress=progress)
        self.gt = np.asarray(dataset.gt[pose], np.float64) if dataset.has_gt else None
        self.inferred = np.asarray(dataset.inferred[pose], np.float64)
        self.inferred_sub = texcoords.positions(self.inferred)
        self.body = None if dataset.body is None else (dataset.body.pose(pose), dataset.body.faces)

    def release(self) -> None:
        self.synth.release()

    def texcoords(self, eye: Camera) -> tuple[np.ndarray, dict[str, float]]:

        weights = weights_for_centre(self.rig, self.array, eye.center)
        d, _ = self.synth.view(self.state, eye, weights)
        return self.tc.uv + d, weights

    def render(self, eye: Camera, with_references: bool = True) -> dict:
        T, weights = self.texcoords(eye)
        gl, body = self.synth.gl, self.body
        out = {"weights": weights, "texcoords": _render(gl, self.inferred_sub, self.tc.faces, T, eye, body)}
        shapes = [x for x in (self.gt, self.inferred) if x is not None]
        if with_references:
            if self.gt is not None:
                out["gt"] = _render(gl, self.gt, self.dataset.faces, self.dataset.uv, eye, body)
            out["inferred"] = _render(gl, self.inferred, self.dataset.faces, self.dataset.uv, eye, body)
        out["cloth"] = ()
        if body is not None and with_references:  # where the cloth shows: the scores' box

            out["cloth"] = tuple(rasterize(gl, x, self.dataset.faces, eye, attributes=False, occluder=body).mask
                                 for x in shapes)
        return out


def _path_weights(names: list[str], per_segment: int) -> list[dict[str, float]]:
    """Weights moving linearly through the cameras in order and back to the first."""
    loop = names + [names[0]] if len(names) > 2 else names + names[-2::-1]
    out = []
    for a, b in zip(loop[:-1], loop[1:]):
        for i in range(per_segment):
            t = i / per_segment
            w = {n: 0.0 for n in names}
            w[a] += 1 - t
            w[b] += t
            out.append(w)
    return out


@writer("preview", inputs=lambda a: (a["dataset"], a["texcoords"], a["rig"]))
def stereo_preview(dataset, rig: Rig, texcoords, pose: int, out: str | os.PathLike, *,
                   weights: Mapping[str, float] | None = None, options: PreviewOptions = PreviewOptions(),
                   progress: bool = True,
                   overwrite: bool = False) -> Preview:
    """`mvtex preview`: the stereo pair of one pose (see the module docstring).

    Args:
        dataset: `Dataset` (gt is read for the reference renders and the scores; an
            inference set gets the pictures without them, its scores None).
        rig: the array. texcoords: the array's `TexcoordSet`.
        pose: dataset pose index (one of the set's poses).
        out: output directory; an existing one must be an earlier preview (it is replaced),
            or empty, or with `overwrite` another command's output (the writer policy of
            `mvtex.util.output`: never files mvtex did not write, never an input).
        weights: the viewpoint (array camera -> weight); default equal over the array.

    Returns:
        A `Preview`; `.to_json()` is preview.json (and `mvtex preview --json`).
    """

    dataset = as_dataset(dataset)
    rig = as_rig(rig)
    texcoords = as_texcoords(texcoords)
    pose = as_index(pose, "pose")
    out = as_path(out, "out")
    check_instance(options, PreviewOptions, "options")

    pose = int(pose)
    if not 0 <= pose < dataset.num_poses:
        raise InputError(dataset.path, f"pose {pose} is outside [0, {dataset.num_poses})")
    texcoords.row(pose)
    texcoords.check_rig(rig)
    texcoords.check_dataset(dataset)
    out = Path(out)
    array = [c for c in rig.names if c in texcoords.cameras]
    if weights is None:
        weights = {c: 1.0 / len(array) for c in array}
    weights = check_weights(weights, rig)
    absent = [c for c in weights if c not in texcoords.cameras]
    if absent:
        raise InputError(texcoords.path, f"no texcoords for camera {', '.join(absent)} in this set")
    if options.method == "reconstruct" and len(array) < 2:
        raise InputError(texcoords.path, "method reconstruct needs texcoords of at least 2 rig cameras")
    viewpoint = interpolate_camera(rig, weights, "viewpoint")
    left, right = eye_cameras(viewpoint, options.ipd)
    check_outside_body(rig, dataset, [pose])
    check_outside_body(Rig((left, right), "the preview's eyes"), dataset, [pose])
    cloth = np.asarray(dataset.inferred[pose], np.float64)
    for eye in (left, right):
        if not eye.sees(cloth):  # scores of two empty pictures would say "identical"
            raise OptionError("ipd", f"{options.ipd:g} m puts the {eye.name} eye where it sees none of the cloth of "
                              f"pose {pose}; give a smaller ipd or another viewpoint")
    eyes = _Eyes(dataset, rig, texcoords, pose, options.method, array, progress)
    try:
        renders = {"left": eyes.render(left), "right": eyes.render(right)}
        scores = {}
        shown = ("gt", "inferred", "texcoords") if dataset.has_gt else ("inferred", "texcoords")
        for name, r in renders.items():
            box = garment_box([r[k] for k in shown], options.margin, r["cloth"])
            ssim = psnr = None
            if dataset.has_gt:
                s_inf, p_inf = image_scores(r["gt"], r["inferred"], box)
                s_tc, p_tc = image_scores(r["gt"], r["texcoords"], box)
                ssim, psnr = (s_inf, s_tc), (p_inf, p_tc)
            H, W = r["inferred"].shape[:2]
            scores[name] = EyeScores(ssim=ssim, psnr=psnr, weights=r["weights"],
                                     box=(int(box[0].start or 0), int(box[0].stop or H), int(box[1].start or 0),
                                          int(box[1].stop or W)))
        files = ["stereo.png", "anaglyph.png", "comparison.png", "preview.json"] + (["path.gif"] if options.path else [])
        converged = convergence(viewpoint, options.ipd, cloth)
        report = Preview(pose=pose, eyes=scores, viewpoint={"weights": weights, "centre": viewpoint.center.tolist()},
                         method=options.method, source=texcoords.source, texcoords=str(texcoords.path),
                         options=options, files=files, convergence=converged, ground_truth=dataset.has_gt)
        with atomic_path(out) as tmp:
            tmp.mkdir()
            L, R = renders["left"], renders["right"]
            save_png(tmp / "stereo.png", side_by_side([L["texcoords"], R["texcoords"]], gap=0))
            save_png(tmp / "anaglyph.png", anaglyph(L["texcoords"], R["texcoords"], converged["shift_px"]))
            rows = [[L[k], R[k]] for k in shown]
            labels = ["gt", "inferred T_G", f"{texcoords.source} {options.method}"][-len(shown):]
            save_png(tmp / "comparison.png", grid_image(rows, col_labels=["left", "right"], row_labels=labels))
            if options.path:
                _write_path_gif(tmp / "path.gif", eyes, rig, array, options, progress)
            write_json(tmp / "preview.json", report.to_json())
    finally:
        eyes.release()
    return report


def _write_path_gif(path: Path, eyes: _Eyes, rig: Rig, array: list[str], options: PreviewOptions,
                    progress: bool) -> None:
    import cv2  # noqa: PLC0415 (loaded on use)
    import imageio.v3 as iio  # noqa: PLC0415 (loaded on use)

    frames = []
    for w in tqdm(_path_weights(array, options.frames_per_segment), desc="path", unit="frame",
                  disable=not progress, file=sys.stderr):
        viewpoint = interpolate_camera(rig, w, "viewpoint")
        pair = [eyes.render(eye, with_references=False)["texcoords"] for eye in eye_cameras(viewpoint, options.ipd)]
        frame = side_by_side(pair, gap=0)
        frame = cv2.resize(frame, (frame.shape[1] // 2, frame.shape[0] // 2), interpolation=cv2.INTER_AREA)
        text = " ".join(f"{k}={v:.2f}" for k, v in w.items() if v > 0)
        frames.append(label(frame, text, scale=0.4))
    iio.imwrite(path, np.stack(frames), extension=".gif", duration=120, loop=0)
