"""The demo's last stage, "new frames, no ground truth": what a user with trained models and
new frames runs (README, "Run on new frames"). The demo's test frames are written as a
predictor would hand them over, one OBJ of the inferred cloth and one of the body per
frame and the pose vectors in a text file, with no ground truth; then

    mvtex import --out dataset --inferred 'meshes/inferred_*.obj' --body 'meshes/body_*.obj' \\
        --pose-vectors meshes/poses.txt                      (no --gt: an inference set)
    mvtex correct dataset --model geometry --out corrected   (the geometry corrector)
    mvtex predict corrected --model tsnn/left --model tsnn/right --out pred
    mvtex triangulate corrected --texcoords pred --pose 0 --out reconstruction
    mvtex preview corrected --texcoords pred --pose 0 --out preview

into OUT/new_frames/ (without a geometry model, the models run on the imported set itself). `predict` records the models' cameras (pred/rig.yaml), so the two
commands after it need no rig. Each step is skipped when its output is there (the demo
resumes).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from mvtex.data.dataset import load_dataset
from mvtex.data.importer import import_sequences
from mvtex.data.rig import load_rig
from mvtex.data.texcoords import open_texcoords, recorded_rig
from mvtex.recon.pose import triangulate_pose
from mvtex.tsnn.correct import correct
from mvtex.tsnn.predict import predict
from mvtex.util.files import read_json, read_row
from mvtex.util.output import atomic_path
from mvtex.views.preview import stereo_preview

FOLDER = "new_frames"


def write_obj(path: str | os.PathLike, positions: np.ndarray, faces: np.ndarray, uv: np.ndarray | None = None) -> None:
    """A triangle mesh as OBJ text: `v` lines, `vt` lines (per vertex, when given) and `f`
    lines (1-based, `a/a` with uv). Numbers are written with 9 significant digits, so that
    float32 positions and uv read back bit for bit (a model matches its mesh's uv exactly)."""
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in np.asarray(positions, np.float32).tolist()]
    if uv is not None:
        lines += [f"vt {u:.9g} {v:.9g}" for u, v in np.asarray(uv, np.float32).tolist()]
        lines += [f"f {a}/{a} {b}/{b} {c}/{c}" for a, b, c in (np.asarray(faces) + 1).tolist()]
    else:
        lines += [f"f {a} {b} {c}" for a, b, c in (np.asarray(faces) + 1).tolist()]
    Path(path).write_text("\n".join(lines) + "\n")


def write_frames(dataset, poses: Sequence[int], folder: str | os.PathLike) -> Path:
    """The inferred cloth (with its uv), the body (if any) and the pose vectors of some
    poses of a dataset, as a predictor hands them over: FOLDER/inferred_<i>.obj,
    FOLDER/body_<i>.obj and FOLDER/poses.txt (one row per frame), i = 0, 1, ... in the order
    of `poses`. Nothing of gt. Written whole (a temporary folder renamed)."""
    folder = Path(folder)
    with atomic_path(folder) as tmp:
        tmp.mkdir()
        for i, k in enumerate(poses):
            write_obj(tmp / f"inferred_{i:04d}.obj", read_row(dataset.inferred, k), dataset.faces, dataset.uv)
            if dataset.body is not None:
                write_obj(tmp / f"body_{i:04d}.obj", read_row(dataset.body.positions, k), dataset.body.faces)
        np.savetxt(tmp / "poses.txt", np.asarray(dataset.poses[list(poses)], np.float32), fmt="%.9g")
    return folder


def demo_new_frames(dataset, out: str | os.PathLike, models: Sequence[str | os.PathLike], *,
                    geometry: str | os.PathLike | None = None, progress: bool = True) -> dict:
    """Run the stage (module docstring) on the test frames of `dataset` with `models`
    (one-camera models of two or more cameras, trained on the set `geometry` corrected when
    given); returns its summary."""
    root = Path(out) / FOLDER
    test = list(dataset.split["test"])
    meshes = root / "meshes"
    if not (meshes / "poses.txt").is_file():
        write_frames(dataset, test, meshes)
    if not (root / "dataset" / "dataset.json").is_file():
        body = str(meshes / "body_*.obj") if dataset.body is not None else None
        import_sequences(root / "dataset", None, str(meshes / "inferred_*.obj"), poses_file=meshes / "poses.txt",
                         body_glob=body, progress=progress)
    frames = load_dataset(root / "dataset")
    if geometry is not None:
        if not (root / "corrected" / "dataset.json").is_file():
            correct(frames, geometry, root / "corrected", progress=progress)
        frames = load_dataset(root / "corrected")
    pred = root / "pred"
    if not (pred / "texcoords.json").is_file():
        predict(frames, list(models), pred, poses=frames.select("all"), progress=progress)
    tc = open_texcoords(pred, frames.num_vertices)
    rig = load_rig(recorded_rig(pred))
    frame = 0
    if (root / "reconstruction" / "report.json").is_file():
        rec = read_json(root / "reconstruction" / "report.json")
    else:
        rec = triangulate_pose(frames, rig, tc, frame, root / "reconstruction", progress=progress).to_json()
    if (root / "preview" / "preview.json").is_file():
        preview = read_json(root / "preview" / "preview.json")
    else:
        preview = stereo_preview(frames, rig, tc, frame, root / "preview", progress=progress).to_json()
    return {"folder": FOLDER, "frames": frames.num_poses, "from_test_poses": test, "ground_truth": frames.has_gt,
            "cameras": tc.cameras, "models": [str(m) for m in models], "frame": frame,
            "geometry": None if geometry is None else str(geometry),
            "reconstruction": {k: rec[k] for k in ("num_vertices", "num_triangulated", "triangulated_share",
                                                   "mean_reprojection_error_px", "mean_trust", "displacement_m",
                                                   "rmse_m")},
            "preview": {"files": preview["files"], "ssim": preview["eyes"]["left"]["ssim"]}}


def summary_line(stage: dict) -> str:
    """The demo summary's lines of the stage."""
    rec = stage["reconstruction"]
    reproj = rec["mean_reprojection_error_px"]
    trust = rec["mean_trust"]
    return (f"new frames, no ground truth ({stage['frames']} test frames as OBJ + pose vectors, imported without "
            f"--gt, {'corrected by the geometry corrector, ' if stage.get('geometry') else ''}predicted by the models "
            f"of {' and '.join(stage['cameras'])}):\n"
            f"  frame {stage['frame']}: triangulated {100 * rec['triangulated_share']:.1f} % of "
            f"{rec['num_vertices']} vertices, mean reprojection error "
            f"{'n/a' if reproj is None else f'{reproj:.2f} px'}, mean trust {'n/a' if trust is None else f'{trust:.2f}'}, "
            f"moved from the {'corrected' if stage.get('geometry') else 'inferred'} mesh {rec['displacement_m']['mean'] * 1e3:.2f} mm on average "
            f"({rec['displacement_m']['max'] * 1e3:.2f} mm at most); {FOLDER}/reconstruction (PLY, COLMAP), "
            f"{FOLDER}/preview (stereo pair)")
