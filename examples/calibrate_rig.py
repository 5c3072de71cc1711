"""Calibrate a camera array from ChArUco board images, step by step, on a synthetic rig.

    python examples/calibrate_rig.py [OUT]        (default: calibrate-demo/)

With real cameras, steps 1 and 3-6 are the same commands; step 2 is your photographs.

1. The board to print:      mvtex board SPEC --out OUT/board.png
2. Photographs of it:       here rendered with moderngl from a known 4-camera rig (one
                            camera with a barrel-distorting lens) at 12 board poses, with
                            noise: OUT/images/<camera>/frame_NNN.png
3. Calibrate:               mvtex calibrate OUT/images --board SPEC --out OUT/rig.yaml
4. A pinhole rig to render with:
                            mvtex rig OUT/rig.yaml --undistort --out OUT/rig_pinhole.yaml
5. Undistorted photographs (compare them with renders made with rig_pinhole.yaml):
                            mvtex undistort OUT/images --rig OUT/rig.yaml --out OUT/undistorted
6. To COLMAP:               mvtex rig OUT/rig_pinhole.yaml --to-colmap OUT/colmap

The script prints each command as it runs it, then the calibrated rig against the truth.
"""

from __future__ import annotations

import contextlib
import io
import json
import sys
from pathlib import Path

import numpy as np

from mvtex.calibration.board import parse_board_spec
from mvtex.calibration.synthetic import random_board_poses, render_calibration_images
from mvtex.cli import main as mvtex
from mvtex.data.camera import Camera, look_at
from mvtex.data.rig import Rig, load_rig

SPEC = "charuco:9x6:0.05:0.0375:DICT_4X4_50"  # 9x6 squares of 5 cm, 3.75 cm markers
BARREL = (-0.12, 0.05, 0.0, 0.0, 0.0)


def true_rig() -> Rig:
    """Four 640x480 cameras 0.9-1.0 m from the origin (where the board is held), 0.2 m
    apart, each with its own K;
    cam2 has a barrel-distorting lens (k1 -0.12, k2 0.05)."""
    cameras = []
    for name, centre, fx, fy, cx, cy in (("cam0", (-0.3, -0.08, -0.95), 600, 604, 318, 242),
                                         ("cam1", (-0.1, 0.04, -1.0), 640, 640, 325, 238),
                                         ("cam2", (0.1, -0.04, -0.98), 580, 583, 316, 245),
                                         ("cam3", (0.3, 0.08, -0.92), 620, 618, 322, 236)):
        pose = look_at(name, centre, (0, 0, 0), width=640, height=480, focal=fx)
        cameras.append(Camera(name, 640, 480, K=np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), R=pose.R, t=pose.t,
                              dist=np.array(BARREL if name == "cam2" else (0.0,) * 5)))
    return Rig(tuple(cameras))


def render_images(rig: Rig, out: Path, num_poses: int = 12, seed: int = 1) -> Path:
    """The board at `num_poses` poses (tilted up to 30 degrees) seen by every camera, noise
    of 2 gray levels: out/<camera>/frame_NNN.png."""
    spec = parse_board_spec(SPEC)
    poses = random_board_poses(rig, spec, num_poses, seed=seed, max_tilt_deg=30, depth_range_m=(-0.3, 0.05),
                               spread_m=0.12)
    return render_calibration_images(rig, spec, poses, out, noise=2.0, seed=0, progress=True)


def run(*argv: str) -> dict | None:
    """Run an mvtex command (printed as a shell line); its JSON if it prints one."""
    print("$ mvtex " + " ".join(argv), flush=True)
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = mvtex(list(argv))
    if code != 0:
        raise SystemExit(code)
    text = stdout.getvalue().strip()
    return json.loads(text) if "--json" in argv else print(text)


def errors(calibrated: Rig, truth: Rig, reference: str) -> dict:
    """Per camera: focal length error (%), principal point error (px), and the error of
    its pose relative to the reference camera (degrees, mm)."""
    def cam_from_ref(cam: Camera, ref: Camera) -> np.ndarray:
        a, b = np.eye(4), np.eye(4)
        a[:3], b[:3] = cam.cam_from_world, ref.cam_from_world
        return a @ np.linalg.inv(b)

    table = {}
    for cam in calibrated:
        true = truth[cam.name]
        expected = cam_from_ref(true, truth[reference])
        got = cam_from_ref(cam, calibrated[reference])
        dR = expected[:3, :3].T @ got[:3, :3]
        table[cam.name] = {
            "focal_pct": float(100 * np.abs(np.diag(cam.K)[:2] / np.diag(true.K)[:2] - 1).max()),
            "principal_px": float(np.abs(cam.K[:2, 2] - true.K[:2, 2]).max()),
            "rotation_deg": float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))),
            "translation_mm": float(1000 * np.linalg.norm(got[:3, 3] - expected[:3, 3])),
            "k1": float(cam.dist[0]), "k1_true": float(true.dist[0])}
    return table


def main(out: str | Path = "calibrate-demo", num_poses: int = 12) -> dict:
    out = Path(out)
    truth = true_rig()
    # --overwrite: a second run of this example replaces its own files.
    run("board", SPEC, "--out", str(out / "board.png"), "--dpi", "150", "--overwrite")
    print(f"(rendering the board from {len(truth)} cameras at {num_poses} poses: {out / 'images'})")
    render_images(truth, out / "images", num_poses)
    result = run("calibrate", str(out / "images"), "--board", SPEC, "--out", str(out / "rig.yaml"),
                 "--pictures", str(out / "rig_calibration"), "--overwrite", "--quiet", "--json")
    run("rig", str(out / "rig.yaml"), "--undistort", "--out", str(out / "rig_pinhole.yaml"), "--overwrite")
    run("undistort", str(out / "images"), "--rig", str(out / "rig.yaml"), "--out", str(out / "undistorted"), "--quiet")
    run("rig", str(out / "rig_pinhole.yaml"), "--to-colmap", str(out / "colmap"))
    table = errors(load_rig(out / "rig.yaml"), truth, result["reference"])
    print(f"\n{result['num_cameras']} cameras, {result['num_frames']} frames, RMS reprojection "
          f"{result['rms_reprojection_px']:.3f} px; calibrated against the true rig:")
    print("camera  frames  RMS px  focal %  principal px  rotation deg  translation mm  k1 (true)")
    for name, e in table.items():
        c = result["per_camera"][name]
        print(f"{name:6s}  {c['frames']:6d}  {c['rms_px']:6.3f}  {e['focal_pct']:7.3f}  {e['principal_px']:12.2f}  "
              f"{e['rotation_deg']:12.3f}  {e['translation_mm']:14.2f}  {e['k1']:+.3f} ({e['k1_true']:+.2f})")
    print(f"pictures: {out / 'rig_calibration'}/rig.png, residuals.png")
    return {"calibrate": result, "errors": table, "rig": out / "rig.yaml", "images": out / "images"}


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "calibrate-demo")
