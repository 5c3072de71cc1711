"""`mvtex demo`: the whole pipeline on the built-in garment, with pictures to look at.

    synth -> render -> slide (stereo, square4) -> eval + heatmaps -> triangulate (square4)
          -> the learned path, no gt at run time: the geometry corrector -> the corrected set ->
             texture sliding on it (a gp model per stereo camera) -> predict -> eval ->
             triangulate, fused with the corrected mesh
          -> novel views (two-camera plot, four-camera map) -> stereo preview
          -> export (the reconstruction's pose as a glTF scene with its viewer)
          -> new frames, no ground truth: the test frames as OBJ + pose vectors, imported without
             gt, corrected by the geometry corrector, predicted by the models of left and right,
             one frame triangulated and previewed (`mvtex.apps.new_frames`)
          -> report.html

Numbers are over the dataset's test split (the poses no model was fitted to). Each step
writes into OUT and is skipped when its output is already there (evaluations keep their
numbers in OUT/eval/), so an interrupted demo resumes where it stopped and a finished one
reruns in seconds. OUT/demo.json records the options; a rerun with other options is refused
(or, with `overwrite`, starts over) instead of reporting the old run.
"""

from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from mvtex import __version__
from mvtex.apps.new_frames import demo_new_frames, summary_line
from mvtex.apps.options import DemoOptions
from mvtex.apps.report import demo_novel_views, demo_preview, demo_report
from mvtex.data.dataset import default_split, load_dataset
from mvtex.data.mesh import rms_distance
from mvtex.data.rig import builtin_rig_file, load_rig
from mvtex.data.texcoords import open_texcoords
from mvtex.evaluation.evaluate import evaluate
from mvtex.recon.pose import triangulate_pose
from mvtex.recon.triangulate import ReconOptions
from mvtex.render.context import GLContext
from mvtex.render.pose import render_pose
from mvtex.sliding.dataset import slide_complete, slide_dataset
from mvtex.sliding.options import SlideOptions
from mvtex.synth.generate import SynthOptions, write_synth
from mvtex.tsnn.cameras import train_cameras
from mvtex.tsnn.correct import correct
from mvtex.tsnn.corrector import train_geometry
from mvtex.tsnn.options import TrainOptions
from mvtex.tsnn.predict import predict
from mvtex.util.checks import as_path, check_instance
from mvtex.util.errors import InputError
from mvtex.util.files import read_json, write_json
from mvtex.util.output import MARKER, clear_output, writer
from mvtex.views.scene import export_scene


def _step(name: str, progress: bool) -> float:
    if progress:

        print(f"[demo] {name}", file=sys.stderr, flush=True)
    return time.perf_counter()


def _evaluated(out: Path, name: str, compute) -> dict:
    """The headline numbers of evaluation `name`: read from OUT/eval/<name>.json when an
    earlier run wrote them, else `compute()` (an `Evaluation`) summarised and written there."""

    path = out / "eval" / f"{name}.json"
    if path.is_file():
        return read_json(path)
    result = _short(compute())
    write_json(path, result)
    return result


@writer("demo", in_place=True)
def run_demo(out: str | os.PathLike, options: DemoOptions = DemoOptions(), progress: bool = True, *,
             overwrite: bool = False) -> dict:
    """Run the demo into `out`; returns a summary dict (also written to OUT/summary.json).

    A folder holding an earlier demo is resumed when its demo.json records the same options;
    with other options it is refused (InputError), or with `overwrite` emptied of what the
    demo wrote there and run again. Never a folder holding files mvtex did not write.
    """

    out = as_path(out, "out")
    check_instance(options, DemoOptions, "options")

    out = Path(out)
    _check_resume(out, options, overwrite)
    timings: dict[str, float] = {}
    summary: dict = {"out": str(out)}

    t = _step("synthesizing the built-in garment", progress)
    data = out / "shirt"
    if not (data / "dataset.json").exists():
        write_synth(data, SynthOptions(num_poses=options.num_poses, seed=options.seed), progress=progress)
    dataset = load_dataset(data)
    timings["synth"] = time.perf_counter() - t
    test = dataset.split["test"]
    test_pose = test[0]
    summary["dataset"] = {"path": str(data), "num_poses": dataset.num_poses, "num_vertices": dataset.num_vertices,
                          "test_pose": test_pose, "split": {k: len(v) for k, v in dataset.split.items()}}

    stereo = load_rig(builtin_rig_file("stereo"))
    square = load_rig(builtin_rig_file("square4"))

    t = _step(f"rendering pose {test_pose} from the stereo rig", progress)
    if not (out / "render" / "render.json").is_file():
        render_pose(dataset, stereo, test_pose, out / "render", progress=progress)
    timings["render"] = time.perf_counter() - t

    poses = dataset.select("all")  # slid on every pose: the model learns from the training split's
    results = {}
    for rig_name, rig in (("stereo", stereo), ("square4", square)):
        t = _step(f"texture sliding, {rig_name} rig, {len(poses)} poses, 1 subdivision", progress)
        tc_path = out / f"ts_{rig_name}"
        if not slide_complete(dataset, rig, tc_path, poses=poses, options=SlideOptions(subdiv=1)):
            slide_dataset(dataset, rig, tc_path, poses=poses, options=SlideOptions(subdiv=1), progress=progress)
        timings[f"slide_{rig_name}"] = time.perf_counter() - t
        t = _step(f"evaluating texture sliding on the {rig_name} rig, test split ({len(test)} poses)", progress)
        tc = open_texcoords(tc_path, dataset.num_vertices)
        results[rig_name] = _evaluated(out, f"ts_{rig_name}", lambda rig=rig, tc=tc: evaluate(
            dataset, rig, tc, poses=test, progress=progress))
        heat = out / "heatmaps" / rig_name
        if rig_name == "stereo" and not heat.is_dir():
            evaluate(dataset, rig, tc, poses=[test_pose], heatmaps=heat, progress=False)
        timings[f"eval_{rig_name}"] = time.perf_counter() - t
    summary["texture_sliding"] = results

    t = _step(f"triangulating pose {test_pose} from the square4 rig", progress)
    tc = open_texcoords(out / "ts_square4", dataset.num_vertices)
    if (out / "reconstruction" / "report.json").is_file():
        summary["reconstruction"] = read_json(out / "reconstruction" / "report.json")
    else:
        summary["reconstruction"] = triangulate_pose(dataset, square, tc, test_pose, out / "reconstruction",
                                                     ReconOptions(), progress=progress).to_json()
    timings["triangulate"] = time.perf_counter() - t

    if options.tsnn:
        summary["tsnn"], summary["learned"] = _learned(dataset, stereo, out, options, timings, progress)

    t = _step("novel views: two-camera path (stereo) and four-camera map (square4)", progress)
    summary["views"] = demo_novel_views(dataset, stereo, square, out, progress=progress)
    timings["views"] = time.perf_counter() - t
    t = _step(f"stereo preview of pose {test_pose}", progress)
    summary["preview"] = demo_preview(dataset, stereo, out, test_pose, progress=progress)
    timings["preview"] = time.perf_counter() - t
    t = _step(f"exporting pose {test_pose} with the square4 texture sliding as a glTF scene", progress)
    if (out / "scene" / "export.json").is_file():
        summary["scene"] = read_json(out / "scene" / "export.json")
    else:
        summary["scene"] = export_scene(dataset, tc, test_pose, out / "scene", rig=square).to_json()
    timings["export"] = time.perf_counter() - t

    if options.tsnn:

        t = _step("new frames, no ground truth: import without gt, correct, predict, triangulate, preview", progress)
        summary["new_frames"] = demo_new_frames(dataset, out, [out / "tsnn" / c for c in stereo.names],
                                                geometry=out / "geometry", progress=progress)
        timings["new_frames"] = time.perf_counter() - t

    summary["timings_s"] = {k: round(v, 2) for k, v in timings.items()}
    summary["pictures"] = sorted(str(p.relative_to(out)) for p in out.rglob("*.png")
                                 if "heatmaps" in p.parts or p.parent.name in ("render", "reconstruction"))

    t = _step("writing report.html", progress)
    summary["report"] = str(demo_report(out, summary, dataset))
    summary["timings_s"]["report"] = round(time.perf_counter() - t, 2)
    summary["summary_text"] = _text(summary)
    write_json(out / "summary.json", summary)
    return summary


def _learned(dataset, stereo, out: Path, options: DemoOptions, timings: dict, progress: bool) -> tuple[dict, dict]:
    """The learned stage: inferred -> corrected -> + texture sliding -> triangulated, on the
    test poses. Returns the per-camera models' evaluation (`_short`) and each step's numbers."""
    test = [int(k) for k in dataset.split["test"]]
    saved = out / "eval" / "learned.json"  # the stage's numbers, once it is done
    if saved.is_file():
        record = read_json(saved)
        return record["tsnn"], record["learned"]
    t = _step("the geometry corrector (pose -> gt - inferred) and the corrected set", progress)
    if not (out / "geometry" / "config.json").exists():
        train_geometry(dataset, out / "geometry", progress=progress)
    if not (out / "corrected" / "dataset.json").exists():
        correct(dataset, out / "geometry", out / "corrected", progress=progress)
    corrected = load_dataset(out / "corrected")
    timings["corrector"] = time.perf_counter() - t
    t = _step("texture sliding on the corrected set (stereo) and a gp model per camera", progress)
    if not (out / "corrected_ts_stereo" / "texcoords.json").exists():  # the models' targets (train needs val too)
        slide_dataset(corrected, stereo, out / "corrected_ts_stereo",
                      poses=sorted(corrected.split["train"] + corrected.split["val"]),
                      options=SlideOptions(subdiv=1), progress=progress)
    tc = open_texcoords(out / "corrected_ts_stereo", corrected.num_vertices)
    train_cameras(corrected, tc, list(stereo.names), out / "tsnn", TrainOptions(seed=options.seed), progress=progress)
    timings["train"] = time.perf_counter() - t
    t = _step("predicting texcoords for the test poses, evaluating, triangulating", progress)
    pred = out / "tsnn_pred"
    if not (pred / "texcoords.json").exists():
        predict(corrected, [out / "tsnn" / c for c in stereo.names], pred, poses=test, progress=progress)
    tc_pred = open_texcoords(pred, corrected.num_vertices)
    with GLContext() as ctx:
        result = evaluate(corrected, stereo, tc_pred, progress=progress, ctx=ctx)
        if not (out / "heatmaps" / "tsnn").exists():
            evaluate(corrected, stereo, tc_pred, poses=test[:1], heatmaps=out / "heatmaps" / "tsnn", progress=False,
                     ctx=ctx)
        reports = [triangulate_pose(corrected, stereo, tc_pred, k, None, ReconOptions(), progress=False, ctx=ctx)
                   for k in test]

    m = result.material_rmse_m
    original = [rms_distance(corrected.original_inferred[k], corrected.gt[k]) for k in test]
    learned = {"test_poses": len(test), "train_poses": len(dataset.split["train"]), "images": result.num_images,
               "material_mm": {"inferred": round(result.original_inferred["material_rmse_m"].mean * 1e3, 3),
                               "corrected": round(m.inferred.mean * 1e3, 3),
                               "texture_sliding": round(m.texcoords.mean * 1e3, 3)},
               "rmse_mm": {"inferred": round(1e3 * float(np.mean(original)), 3),
                           "corrected": round(1e3 * float(np.mean([r.rmse_m.inferred for r in reports])), 3),
                           "triangulated": round(1e3 * float(np.mean([r.rmse_m.reconstructed for r in reports])), 3)}}
    timings["tsnn_predict_eval"] = time.perf_counter() - t
    short = _short(result)
    short["train_poses"] = len(dataset.split["train"])
    write_json(saved, {"tsnn": short, "learned": learned})
    return short, learned


def _check_resume(out: Path, options: DemoOptions, overwrite: bool) -> None:
    """Resume only a demo of the same options, as demo.json records them and as what it
    wrote bears them out (its dataset's poses and split); record them for a new one."""

    record = {"options": asdict(options), "mvtex": __version__}
    started = any(p.name != MARKER for p in out.iterdir())
    if started:
        try:
            old = read_json(out / "demo.json")
        except InputError:
            old = None
        if old != record:
            was = ", ".join(f"{k}={v}" for k, v in old["options"].items()) \
                if isinstance(old, dict) and isinstance(old.get("options"), dict) else "unknown options"
            differs = f"holds a demo run with other options ({was})"
        else:
            differs = _content_differs(out, options)
        if differs:
            if not overwrite:
                raise InputError(out, f"{differs}; it would be reported as this one: choose another folder, or pass "
                                 "--overwrite to start over")
            clear_output(out, "demo")
    write_json(out / "demo.json", record)


def _content_differs(out: Path, options: DemoOptions) -> str | None:
    """What in a demo folder contradicts `options` (demo.json edited, or the dataset replaced):
    its dataset's pose count and its split (seeded by `options.seed`); None when nothing does."""

    data = out / "shirt"
    if not (data / "dataset.json").exists():
        return None
    try:
        dataset = load_dataset(data, validate=False)
    except InputError as err:
        return f"holds a demo dataset that does not load ({err})"
    split = {k: [int(p) for p in v] for k, v in dataset.split.items()}
    if dataset.num_poses != options.num_poses or split != default_split(options.num_poses, options.seed):
        return (f"holds the demo of a dataset of {dataset.num_poses} poses, not the {options.num_poses} poses of seed "
                f"{options.seed} its demo.json records")
    return None


def _model_current(model: Path, dataset) -> bool:
    """Whether the demo's model at `model` was trained on this dataset's training poses."""

    try:
        meta = json.loads((model / "config.json").read_text())
        return (model / "model.safetensors").is_file() and meta["split"]["train"] == list(dataset.split["train"])
    except (OSError, ValueError, KeyError, TypeError):
        return False


def _short(result) -> dict:
    """The headline numbers of an `Evaluation`, rounded for the summary (split: "test")."""
    s, c, m, a = result.sqrt_mse, result.sqrt_mse_same_chart, result.material_rmse_m, result.material_rmse_assigned_m
    return {"split": "test", "num_images": result.num_images,
            "material_inferred_mm": round(m.inferred.mean * 1e3, 3),
            "material_texcoords_mm": round(m.texcoords.mean * 1e3, 3),
            "ratio_material": round(result.ratio_material, 2),
            "material_assigned_inferred_mm": round(a.inferred.mean * 1e3, 3),
            "material_assigned_texcoords_mm": round(a.texcoords.mean * 1e3, 3),
            "ratio_material_assigned": round(result.ratio_material_assigned, 2),
            "assigned_share": round(result.assigned_share.mean, 4),
            "inferred_e3": round(s.inferred.mean * 1e3, 3),
            "texcoords_e3": round(s.texcoords.mean * 1e3, 3), "ratio": round(result.ratio, 2),
            "same_chart_inferred_e3": round(c.inferred.mean * 1e3, 3),
            "same_chart_texcoords_e3": round(c.texcoords.mean * 1e3, 3),
            "ratio_same_chart": round(result.ratio_same_chart, 2)}


def _pair(r: dict, indent: str = "  ") -> str:
    """The lines of one evaluation: the material error first (all pixels, then the assigned
    triangles), the uv error last (all pixels, then the same-chart pixels)."""
    lines = [(f"material error {r['material_inferred_mm']:.2f} -> {r['material_texcoords_mm']:.2f} mm "
              f"(ratio {r['ratio_material']:.1f}, all pixels)")]
    if r["assigned_share"] < 1:
        lines.append(f"material error, assigned triangles ({100 * r['assigned_share']:.1f} % of pixels) "
                     f"{r['material_assigned_inferred_mm']:.2f} -> {r['material_assigned_texcoords_mm']:.2f} mm "
                     f"(ratio {r['ratio_material_assigned']:.1f})")
    lines.append(f"uv error (e-3) {r['inferred_e3']:.2f} -> {r['texcoords_e3']:.2f} (ratio {r['ratio']:.2f}, all "
                 f"pixels); same chart {r['same_chart_inferred_e3']:.2f} -> {r['same_chart_texcoords_e3']:.2f} "
                 f"(ratio {r['ratio_same_chart']:.1f})")
    return "".join(f"\n{indent}{line}" for line in lines)


def _text(summary: dict) -> str:
    d = summary["dataset"]
    split = d.get("split", {})
    lines = [f"mvtex demo -> {summary['out']}",
             (f"dataset: {d['num_poses']} poses ({split.get('train', '?')} train, {split.get('val', '?')} validation, "
              f"{split.get('test', '?')} test), {d['num_vertices']} vertices; numbers below are over the test split"),
             ("  (inferred -> texcoords; material error: mm on the garment between the material a pixel shows and the "
              "one it should; uv error: the paper's per-pixel texture-coordinate error; same chart: over the pixels "
              "where both meshes show one UV chart, pattern piece)")]
    for rig, r in summary["texture_sliding"].items():
        lines.append(f"texture sliding from ground truth ({rig}, 1 subdivision, test split, {r['num_images']} "
                     f"images):{_pair(r)}")
    rec = summary["reconstruction"]
    lines.append(f"reconstruction from ground-truth sliding (square4, test pose {rec['pose']}): RMSE to gt "
                 f"{rec['rmse_triangulated_m']['inferred']*1e3:.2f} -> {rec['rmse_triangulated_m']['reconstructed']*1e3:.2f} mm "
                 f"on the {rec['num_triangulated']} triangulated vertices, "
                 f"{rec['rmse_m']['inferred']*1e3:.2f} -> {rec['rmse_m']['reconstructed']*1e3:.2f} mm "
                 f"on all {rec['num_vertices']}")
    if "learned" in summary:
        r = summary["learned"]
        mat, rms = r["material_mm"], r["rmse_mm"]

        def step(name: str, key: str, material: bool = True) -> str:
            text = f"material error {mat[key]:.2f} mm (x{mat['inferred'] / mat[key]:.2f})" if material else ""
            if key in rms:
                text += ("; " if text else "") + f"RMSE to gt {rms[key]:.2f} mm (x{rms['inferred'] / rms[key]:.2f})"
            return f"\n  {name}: {text}"

        lines.append(f"learned path, no ground truth at run time ({r['test_poses']} test poses, {r['images']} stereo "
                     f"images; trained on {r['train_poses']} poses; ratios to the inferred mesh):"
                     + step("inferred", "inferred") + step("-> corrected (the geometry corrector)", "corrected")
                     + step("-> + texture sliding (a gp model per camera on the corrected set)", "texture_sliding")
                     + step("-> triangulated (stereo, fused with the corrected mesh)", "triangulated", False))
        lines.append("  the models' accuracy grows with their training poses (docs/tsnn.md)")
    if "views" in summary:
        v = summary["views"]["two_camera"]["midpoint_same_chart_e3"]
        names = {"baseline": "inferred (T_G)",
                 "direct TS": "direct TS (texture sliding from gt at the view itself, the upper bound)"}
        lines.append("novel view at the stereo midpoint, uv error on same-chart pixels (e-3): " +
                     ", ".join(f"{names.get(k, k)} {x:.3f}" for k, x in v.items()))
    if "preview" in summary:
        e = summary["preview"]["eyes"]
        lines.append(f"stereo preview SSIM against gt (inferred -> texcoords): left {e['left']['ssim']['inferred']:.3f} "
                     f"-> {e['left']['ssim']['texcoords']:.3f}, right {e['right']['ssim']['inferred']:.3f} -> "
                     f"{e['right']['ssim']['texcoords']:.3f}")
    if "scene" in summary:
        lines.append(f"scene of test pose {summary['scene']['pose']} to look around in: "
                     f"{Path(summary['out']) / 'scene' / 'viewer.html'}")
    if "new_frames" in summary:

        lines.append(summary_line(summary["new_frames"]))
    if "report" in summary:
        lines.append(f"report: {summary['report']}")
    lines.append("pictures: " + ", ".join(summary["pictures"][:8]) + (" ..." if len(summary["pictures"]) > 8 else ""))
    return "\n".join(lines)
