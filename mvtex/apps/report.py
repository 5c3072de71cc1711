"""A static HTML report of a demo run (`OUT/report.html`), readable offline.

One page: every stage's numbers as tables and its pictures (relative links to the PNG/GIF
files in OUT), and two interactive 3-D views drawn by mvtex's viewer on three.js (vendored in
`mvtex/vendor`, the viewer's own scripts in `mvtex/web`, all copied to OUT/viewer/): the scene
of `mvtex export` for the reconstruction's pose (the cameras' texture sliding blended by the eye),
and gt, the inferred mesh and the reconstruction side by side. The GLBs are also embedded in the
page, because browsers refuse `fetch` of local files opened from `file://`.
"""

from __future__ import annotations

import base64
import html
import json
import os
import re
import shutil
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from mvtex.data.texcoords import open_texcoords
from mvtex.formats.glb import export_glb
from mvtex.render.pictures import NOT_TRIANGULATED_RGB, TRIANGULATED_RGB, ColorScale, colorbar, comparison_scales
from mvtex.render.shading import BODY_RGB
from mvtex.util.files import read_json, write_json
from mvtex.util.output import atomic_path
from mvtex.views.cameras import between_weights, grid_weights, view_names
from mvtex.views.measure import measure_views, plot_grid, plot_path
from mvtex.views.preview import PreviewOptions, stereo_preview
from mvtex.views.scene import SCRIPTS, glb_element, script_path

VIEWER_FILES = tuple(SCRIPTS) + (("vendor", "three.LICENSE"),)
# The order of the meshes in the comparison picture and in the 3-D view, with their labels.
MESH_ORDER = (("gt", "gt"), ("inferred", "inferred"), ("reconstruction", "reconstruction"))


def copy_viewer(out: str | os.PathLike) -> Path:
    """Copy the viewer's scripts (three.js and its licence, mvtex's viewer) to OUT/viewer/;
    returns that folder."""

    folder = Path(out) / "viewer"
    for where, name in VIEWER_FILES:
        with atomic_path(folder / name) as tmp:  # written whole, and recorded in the demo's manifest
            shutil.copyfile(script_path(where, name), tmp)
    return folder


def table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """An HTML table; floats printed with 4 significant digits."""
    def cell(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        return "—" if v is None else html.escape(str(v))

    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{cell(v)}</td>" for v in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def figure(src: str, caption: str, width: str = "100%") -> str:
    return (f'<figure><img src="{html.escape(src)}" alt="{html.escape(caption)}" style="max-width:{width}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>")


def png_data_uri(image: np.ndarray) -> str:
    """An RGB uint8 image as a data URI (PNG), for pictures that exist only in the page."""
    import cv2  # noqa: PLC0415 (loaded on use)

    ok, data = cv2.imencode(".png", np.ascontiguousarray(np.asarray(image, np.uint8)[..., ::-1]))
    return "data:image/png;base64," + base64.b64encode(data.tobytes()).decode("ascii")


def model_view(glb: Path, caption: str, *, frame: dict, legend_png: str | None = None,
               labels: dict[str, str] | None = None, element_id: str = "meshes") -> str:
    """The 3-D view of a GLB of meshes side by side (`export_glb`), in vertex colours.

    Args:
        frame: {"target": (x, y, z), "radius": r, "fov_deg": f} (meters, the GLB's axes): the
            camera looks at target from r away (`garments_frame`).
        legend_png: a picture (URI) shown beside the view.
        labels: node name -> the label written above that mesh.
    """
    side = (f'<img src="{legend_png}" alt="colour scale of the 3-D view" style="height:440px;flex:0 0 auto">'
            if legend_png else "")
    call = (f"mvtexViewer.openMeshes(document.getElementById('{element_id}'), "
            f"document.getElementById('{element_id}-glb').textContent, {json.dumps(frame)}, {json.dumps(labels or {})});")
    return (f'<figure><div style="display:flex;gap:0"><div id="{element_id}" style="flex:1 1 auto;height:440px">'
            f'</div>{side}</div>{glb_element(glb, element_id + "-glb")}<script>{call}</script>'
            f'<figcaption>{html.escape(caption)} (drag to turn, scroll to zoom; the file: '
            f'<a href="{html.escape(glb.name)}">{html.escape(glb.name)}</a>)</figcaption></figure>')


def scene_view(folder: Path, out: Path, caption: str, element_id: str = "scene") -> str:
    """The viewer of an `mvtex export` folder (its scene.glb embedded), opening at the
    default viewpoint (equal weights over the cameras); it leaves the page's address alone."""
    rel = folder.relative_to(out)
    call = (f"mvtexViewer.openScene(document.getElementById('{element_id}'), "
            f"document.getElementById('{element_id}-glb').textContent, new URLSearchParams(''), {{page: false}});")
    return (f'<figure><div id="{element_id}" style="height:600px"></div>{glb_element(folder / "scene.glb", element_id + "-glb")}'
            f'<script>{call}</script><figcaption>{html.escape(caption)} (the files: '
            f'<a href="{html.escape(str(rel / "scene.glb"))}">scene.glb</a>, '
            f'<a href="{html.escape(str(rel / "viewer.html"))}">viewer.html</a>)</figcaption></figure>')


_STYLE = """
body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222;line-height:1.45}
h1{margin-bottom:0.2em} h2{border-bottom:1px solid #ccc;padding-bottom:0.2em;margin-top:2em}
table{border-collapse:collapse;margin:0.8em 0} th,td{border:1px solid #ccc;padding:0.25em 0.6em;text-align:right}
th{background:#f1f1f4} td:first-child,th:first-child{text-align:left}
figure{margin:1em 0} figure img{border:1px solid #ddd} figcaption{font-size:0.9em;color:#555}
.row{display:flex;gap:1em;flex-wrap:wrap} .row figure{flex:1 1 300px}
code{background:#f4f4f6;padding:0 0.2em}
"""


# After loading, the page records on <html> how many images failed to load: a headless
# browser's DOM dump then tells whether the page is whole (the 3-D views record their own state
# in their elements' data-viewer).
_CHECK = """<script>window.addEventListener('load', function () {
  var broken = Array.prototype.filter.call(document.images, function (i) { return !i.complete || !i.naturalWidth; });
  document.documentElement.setAttribute('data-broken-images', String(broken.length));
});</script>"""


def page(title: str, sections: Sequence[tuple[str, str]], viewer: bool) -> str:
    script = ("".join(f'<script src="viewer/{name}"></script>' for _, name in SCRIPTS) if viewer else "") + _CHECK
    body = "".join(f"<h2>{html.escape(h)}</h2>{content}" for h, content in sections)
    return (f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>{html.escape(title)}</title>"
            f"<style>{_STYLE}</style>{script}</head><body><h1>{html.escape(title)}</h1>{body}</body></html>\n")


def write_html(path: str | os.PathLike, text: str) -> Path:

    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path


def missing_images(html_text: str, folder: str | os.PathLike) -> list[str]:
    """The `<img src>` of a page that are not files under `folder` (data URIs count as present)."""

    folder = Path(folder)
    out = []
    for src in re.findall(r'<img[^>]*\ssrc="([^"]+)"', html_text):
        src = html.unescape(src)
        if not src.startswith("data:") and not (folder / src).is_file():
            out.append(src)
    return out


def demo_novel_views(dataset, stereo, square, out: str | os.PathLike, *, path_poses: int = 2, grid_poses: int = 1,
                     progress: bool = True) -> dict:
    """The two-camera plot (stereo, 5 views, first `path_poses` test poses) and the
    four-camera map (square4, 3×3 views, first `grid_poses` test poses) into OUT/views/.
    Skipped when OUT/views/views.json exists (the demo resumes)."""

    folder = Path(out) / "views"
    if (folder / "views.json").is_file():
        return read_json(folder / "views.json")
    folder.mkdir(parents=True, exist_ok=True)
    test = dataset.split["test"]
    weights = between_weights("left", "right", 5)
    tc = open_texcoords(Path(out) / "ts_stereo", dataset.num_vertices)
    two = measure_views(dataset, stereo, tc, weights, view_names(5), poses=test[:path_poses], progress=progress)
    plot_path(two, folder / "two_camera.png", [w["right"] for w in weights], a="left", b="right")
    corners = ["tl", "tr", "bl", "br"]
    grid = grid_weights(*corners, 3)
    tc4 = open_texcoords(Path(out) / "ts_square4", dataset.num_vertices)
    four = measure_views(dataset, square, tc4, grid, view_names(9), poses=test[:grid_poses], progress=progress)
    plot_grid(four, folder / "four_camera.png", 3, corners)
    result = {
        "two_camera": {**two, "picture": "views/two_camera.png",
                       "midpoint_same_chart_e3": {k: v[2] * 1e3 for k, v in two["sqrt_mse_same_chart"].items()},
                       "cameras_same_chart_e3": {k: (v[0] + v[-1]) / 2 * 1e3
                                                 for k, v in two["sqrt_mse_same_chart"].items()}},
        "four_camera": {**four, "picture": "views/four_camera.png",
                        "mean_same_chart_e3": {k: float(np.mean(v)) * 1e3
                                               for k, v in four["sqrt_mse_same_chart"].items()}},
    }
    write_json(folder / "views.json", result)
    return result


def demo_preview(dataset, stereo, out: str | os.PathLike, pose: int, *, progress: bool = True) -> dict:
    """`mvtex preview` of one pose from the stereo TS set into OUT/preview/ (with path.gif);
    skipped when OUT/preview/preview.json exists."""

    folder = Path(out) / "preview"
    if (folder / "preview.json").is_file():
        return read_json(folder / "preview.json")
    tc = open_texcoords(Path(out) / "ts_stereo", dataset.num_vertices)
    return stereo_preview(dataset, stereo, tc, pose, folder, options=PreviewOptions(path=True, frames_per_segment=4),
                          progress=progress).to_json()


def _pictures(out: Path, folder: str, limit: int) -> list[str]:
    return [str(p.relative_to(out)) for p in sorted((out / folder).glob("*.png"))[:limit]] if (out / folder).is_dir() else []


def demo_report(out: str | os.PathLike, summary: dict, dataset) -> Path:
    """Write OUT/report.html (and OUT/viewer/, OUT/reconstruction.glb) from a demo's summary."""
    out = Path(out)
    sections: list[tuple[str, str]] = []
    d = summary["dataset"]
    split = d.get("split", {})
    sections.append(("Dataset and renders", table(["poses", "train / validation / test", "vertices", "test pose shown"],
                                                  [[d["num_poses"], " / ".join(str(split.get(k, "?")) for k in
                                                                               ("train", "val", "test")),
                                                    d["num_vertices"], d["test_pose"]]]) +
                     (figure("render/overview.png", "gt and inferred cloth from the stereo rig: textured (rows 1-2), "
                                                    "and the untextured geometry under a key light, zoomed on the "
                                                    "garment (rows 3-4), where the folds gt has and the inferred "
                                                    "mesh lacks show")
                      if (out / "render" / "overview.png").is_file() else "")))
    measures = ("<p>Every number is over the test split (the poses no model was fitted to), per image, mean. "
                "<b>Material error</b>: the distance on the garment (mm) between the material a pixel shows and the "
                "one it should show. <b>uv error</b>: the paper's per-pixel texture-coordinate error (SqrtMSE), "
                "×10⁻³ uv units. <b>Same chart</b>: over the pixels where both meshes show one UV chart (pattern "
                "piece); where they show different charts the uv difference is a distance across the atlas, not on "
                "the cloth. <b>Assigned triangles</b>: pixels of triangles whose corners the rays assigned.</p>")

    def ts_tables(items) -> str:
        """Two tables: the material error (all pixels, assigned triangles), the uv error."""
        items = list(items)
        material = [[name, r["num_images"], r.get("material_inferred_mm"), r.get("material_texcoords_mm"),
                     r.get("ratio_material"), r.get("material_assigned_inferred_mm"),
                     r.get("material_assigned_texcoords_mm"), r.get("ratio_material_assigned"),
                     None if r.get("assigned_share") is None else 100 * r["assigned_share"]] for name, r in items]
        uv = [[name, r["inferred_e3"], r["texcoords_e3"], r["ratio"], r["same_chart_inferred_e3"],
               r["same_chart_texcoords_e3"], r["ratio_same_chart"]] for name, r in items]
        return (table(["", "test images", "material error: inferred mm", "texcoords mm", "ratio",
                       "assigned triangles: inferred mm", "texcoords mm", "ratio", "% of pixels"], material)
                + table(["", "uv error: inferred e-3", "texcoords e-3", "ratio", "same chart: inferred e-3",
                         "texcoords e-3", "ratio"], uv))

    ts = summary.get("texture_sliding", {})
    heat = '<div class="row">' + "".join(
        figure(p, f"heatmaps of test pose {d['test_pose']}, camera {Path(p).stem.split('_')[-1]}: the inferred mesh "
                  "(T_G) | texture sliding; top the uv error on same-chart pixels, bottom the material error, each on "
                  "one logarithmic scale in every heatmap; the legend names the other colours")
        for p in _pictures(out, "heatmaps/stereo", 2)) + "</div>"
    sections.append(("Texture sliding from ground truth", measures + ts_tables(ts.items()) + heat))

    rec = summary.get("reconstruction")
    if rec:
        rows = [["all vertices", rec["rmse_m"]["inferred"] * 1e3, rec["rmse_m"]["reconstructed"] * 1e3],
                ["triangulated vertices", rec["rmse_triangulated_m"]["inferred"] * 1e3,
                 rec["rmse_triangulated_m"]["reconstructed"] * 1e3]]
        content = (f"<p>test pose {rec['pose']}, square4 rig: {rec['num_triangulated']} of {rec['num_vertices']} "
                   f"vertices triangulated, mean reprojection error "
                   f"{rec['mean_reprojection_error_px'] or float('nan'):.3f} px.</p>"
                   + table(["RMSE vs gt (mm)", "inferred", "reconstructed"], rows))
        ply = out / "reconstruction" / "reconstruction.ply"
        if ply.is_file():
            glb, frame, scale = _reconstruction_glb(out, ply, dataset, int(rec["pose"]))

            content += model_view(glb, "left to right as in comparison.png: gt (green: triangulated vertices, grey: "
                                       "not), inferred, reconstruction; coloured by the distance to gt on the scale of "
                                       "comparison.png (the bar beside the view)", frame=frame,
                                  legend_png=png_data_uri(colorbar(440, scale, width=120)),
                                  labels=dict(MESH_ORDER))
        if (out / "reconstruction" / "comparison.png").is_file():
            content += figure("reconstruction/comparison.png", "gt | inferred | reconstruction: texture; the geometry "
                              "under a key light, and zoomed where gt's folds and the inferred mesh's differ most; "
                              "strain; distance to gt (each with its colour bar; legend below)", width="90%")
        sections.append(("Reconstruction", content))

    scene = summary.get("scene")
    if scene and (out / "scene" / "scene.glb").is_file():
        sections.append(("The scene to look around in", (
            f"<p>Test pose {scene['pose']} as <code>mvtex export</code> writes it: the inferred mesh with one set of "
            f"texture coordinates per square4 camera ({', '.join(scene['cameras'])}), from texture sliding. As the "
            "view turns, the page blends the cameras' texture coordinates with the weights <code>mvtex preview</code> "
            "gives the eye's position; at a camera's own viewpoint it shows that camera's texture sliding. The "
            "buttons switch to the mesh's own texture coordinates (T_G), hide the body, or show a stereo pair.</p>"
            + scene_view(out / "scene", out, "the scene viewer (scene.glb, three.js)"))))

    if "tsnn" in summary:
        r = summary["tsnn"]
        sections.append(("The learned path: the geometry corrector, texture sliding on top (stereo, test poses)",
                         _learned_table(summary.get("learned")) +
                         f"<p>a gp model per camera, trained on {r.get('train_poses')} poses of the set the geometry "
                         "corrector made; the baseline (inferred) is the corrected mesh.</p>" + ts_tables([("gp models", r)]) +
                         "".join(figure(p, f"error heatmaps {Path(p).stem}: the corrected mesh (T_G) | the gp models' "
                                           "prediction", width="60%")
                                 for p in _pictures(out, "heatmaps/tsnn", 1))))

    views = summary.get("views")
    if views:
        two = views["two_camera"]
        curves = list(two["midpoint_same_chart_e3"])
        names = {"baseline": "inferred (T_G)"}
        rows = [[names.get(c, c), two["cameras_same_chart_e3"][c], two["midpoint_same_chart_e3"][c],
                 two["sqrt_mse"][c][2] * 1e3] for c in curves]
        content = ("<p>Views between the stereo cameras (t = 0 left, 1 right): <b>blend</b> is the paper's "
                   "T_N(v) = Σ w_p T_N(v_p); <b>reconstruct</b> triangulates the pose from the array and reads the "
                   "material where each view's ray meets it; <b>direct TS</b> is texture sliding from ground truth at "
                   "the view itself (the upper bound, not available at run time); inferred (T_G) is the mesh's own "
                   "texture coordinates.</p>" +
                   table(["uv error e-3", "at the cameras (same chart)", "midpoint (same chart)", "midpoint (all pixels)"],
                         rows) + figure(two["picture"], "uv error along the path between the stereo cameras"))
        four = views.get("four_camera")
        if four:
            content += table(["3x3 views over square4", "mean uv error, same chart, e-3"],
                             [[c, v] for c, v in four["mean_same_chart_e3"].items()])
            content += figure(four["picture"], "four-camera map: uv error on same-chart pixels of 3x3 views over square4")
        sections.append(("Novel views", content))

    prev = summary.get("preview")
    if prev:
        rows = [[eye, s["ssim"]["inferred"], s["ssim"]["texcoords"], s["psnr"]["inferred"], s["psnr"]["texcoords"]]
                for eye, s in prev["eyes"].items()]
        shift = prev.get("convergence", {})
        content = (f"<p>test pose {prev['pose']}, viewpoint {prev['viewpoint']['weights']}, ipd {prev['ipd']} m, method "
                   f"{prev['method']}; scores over the garment's bounding box against the gt render.</p>" +
                   table(["eye", "SSIM inferred", "SSIM texcoords", "PSNR inferred (dB)", "PSNR texcoords (dB)"], rows) +
                   '<div class="row">' + figure("preview/stereo.png", "stereo pair (left | right)") +
                   figure("preview/anaglyph.png", "red-cyan anaglyph" + (
                       f", converged at the garment ({shift['depth_m']:.2f} m: each eye shifted by "
                       f"{shift['shift_px'] / 2:.1f} px)" if shift else "")) + "</div>" +
                   '<div class="row">' + figure("preview/comparison.png", "gt / inferred with T_G / with the eyes' texcoords") +
                   (figure("preview/path.gif", "the viewpoint moving through the array")
                    if (out / "preview" / "path.gif").is_file() else "") + "</div>")
        sections.append(("Stereo preview", content))

    if "new_frames" in summary:
        sections.append(_new_frames_section(summary["new_frames"]))

    timings = summary.get("timings_s", {})
    sections.append(("Timings", table(["step", "seconds"], [[k, float(v)] for k, v in timings.items()])))
    copy_viewer(out)
    text = page("mvtex demo report", sections, viewer=True)
    return write_html(out / "report.html", text)


def _learned_table(learned: dict | None) -> str:
    """The demo's learned path step by step (`mvtex.apps.demo`): material error and RMSE to
    gt of each step, with its ratio to the inferred mesh."""
    if not learned:
        return ""
    mat, rms = learned["material_mm"], learned["rmse_mm"]
    steps = (("inferred", "inferred"), ("-> corrected (the geometry corrector)", "corrected"),
             ("-> + texture sliding (a gp model per camera)", "texture_sliding"),
             ("-> triangulated (fused with the corrected mesh)", "triangulated"))

    def cell(values: dict, key: str) -> str:
        return "" if key not in values else f"{values[key]:.2f} (x{values['inferred'] / values[key]:.2f})"

    rows = [[name, cell(mat, key), cell(rms, key)] for name, key in steps]
    render = ("the corrected mesh with its own texture coordinates" if mat["corrected"] <= mat["texture_sliding"]
              else "the gp models' texture coordinates on the corrected mesh")
    shape = ("the reconstruction fused with the corrected mesh" if rms["triangulated"] < rms["corrected"]
             else "the corrected mesh")
    return (f"<p>{learned['test_poses']} test poses, {learned['images']} stereo images, trained on "
            f"{learned['train_poses']} poses; no ground truth at run time. Ratios are to the inferred mesh.</p>"
            + table(["step", "material error mm", "RMSE to gt mm (all vertices)"], rows)
            + f"<p>Here the best for rendering is {render}, and for the 3-D shape {shape} (which path serves "
            "what on larger sets: docs/tsnn.md).</p>")


def _new_frames_section(stage: dict) -> tuple[str, str]:
    """The section of the demo's new-frames stage (`mvtex.apps.new_frames`): what it can say
    without gt, and its preview."""
    rec, folder = stage["reconstruction"], stage["folder"]
    rows = [[stage["frame"], 100 * rec["triangulated_share"], rec["mean_reprojection_error_px"], rec["mean_trust"],
             rec["displacement_m"]["mean"] * 1e3, rec["displacement_m"]["max"] * 1e3]]
    content = (f"<p>{stage['frames']} test frames written as OBJ (inferred cloth, body) and pose vectors, imported "
               "without ground truth, "
               + ("corrected by the geometry corrector, " if stage.get("geometry") else "")
               + f"predicted by the per-camera models of {', '.join(stage['cameras'])}; frame {stage['frame']} triangulated and previewed. What can be said "
               "without gt:</p>"
               + table(["frame", "triangulated %", "reprojection px", "mean trust", "moved mean mm", "moved max mm"],
                       rows)
               + '<div class="row">' + figure(f"{folder}/preview/stereo.png", "stereo pair (left | right)")
               + figure(f"{folder}/preview/comparison.png", "inferred with T_G / with the eyes' texcoords") + "</div>")
    return "New frames, no ground truth", content


def _reconstruction_glb(out: Path, ply: Path, dataset, pose: int):
    """OUT/reconstruction.glb: gt, inferred and reconstruction side by side (`MESH_ORDER`, as in
    comparison.png), coloured as the
    reconstruction's comparison.png (gt: triangulated vertices green; the others: distance
    to gt on the comparison's error scale, read from reconstruction/comparison.json). Returns
    (path, frame for `model_view`, the error `ColorScale`)."""
    import trimesh  # noqa: PLC0415 (loaded on use)

    loaded = trimesh.load(ply, process=False)
    rec = np.asarray(loaded.vertices, np.float64)
    gt = np.asarray(dataset.gt[pose], np.float64)
    inferred = np.asarray(dataset.inferred[pose], np.float64)
    scale = None
    try:
        saved = read_json(ply.parent / "comparison.json").get("scales", {}).get("error")
        if isinstance(saved, dict):
            scale = ColorScale(float(saved["vmin"]), float(saved["vmax"]), bool(saved["log"]), str(saved["colormap"]),
                               str(saved["title"]), str(saved["unit"]), float(saved["factor"]))
    except Exception:  # no comparison.json, or an unreadable one: fit the scale again
        scale = None
    if scale is None:
        scale = comparison_scales(dataset.faces, gt, inferred, rec, None)["error"]
    try:
        triangulated = np.asarray(loaded.metadata["_ply_raw"]["vertex"]["data"]["triangulated"], bool)
    except (KeyError, TypeError, ValueError):
        triangulated = np.zeros(len(gt), bool)
    gt_colors = np.where(triangulated[:, None], np.array([TRIANGULATED_RGB]),
                         np.array([NOT_TRIANGULATED_RGB])).astype(np.uint8)
    colours = {"gt": gt_colors, "inferred": scale.colors(np.linalg.norm(inferred - gt, axis=1)),
               "reconstruction": scale.colors(np.linalg.norm(rec - gt, axis=1))}
    positions = {"gt": gt, "inferred": inferred, "reconstruction": rec}
    meshes = [(name, positions[name], dataset.faces, colours[name]) for name, _ in MESH_ORDER]
    body = None
    if dataset.body is not None:

        body = (dataset.body.pose(pose), dataset.body.faces, BODY_RGB)
    path = export_glb(out / "reconstruction.glb", meshes, body=body)
    return path, garments_frame([m[1] for m in meshes]), scale


def garments_frame(positions: Sequence[np.ndarray], *, spacing: float = 1.25, fov_deg: float = 30.0,
                   aspect: float = 2.2) -> dict:
    """Where `model_view`'s camera looks to frame the garments of `export_glb` (laid side by
    side, each centred at its mean) and not the bodies around them: the target is the
    garments' box centre, the distance fits their row in a view of `aspect` (width / height)
    with a vertical field of view of `fov_deg`, with 10 % to spare."""
    boxes = [(np.asarray(p).min(axis=0) - np.asarray(p).mean(axis=0), np.asarray(p).max(axis=0) - np.asarray(p).mean(axis=0))
             for p in positions]
    width = max(float(hi[0] - lo[0]) for lo, hi in boxes)
    height = max(float(hi[1] - lo[1]) for lo, hi in boxes)
    row = (len(positions) - 1) * spacing * width + width
    centre_y = float(np.mean([(lo[1] + hi[1]) / 2 for lo, hi in boxes]))
    half = np.radians(fov_deg) / 2
    radius = 1.1 * max(height / 2 / np.tan(half), row / 2 / (aspect * np.tan(half)))
    return {"target": (0.0, centre_y, 0.0), "radius": float(radius), "fov_deg": fov_deg}
