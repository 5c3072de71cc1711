"""What `mvtex calibrate` writes: the rig YAML and, on request, a folder with the record of
the calibration and its pictures (the rig, the reprojection residuals).
"""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path

import numpy as np

from mvtex.calibration.board import BoardSpec
from mvtex.calibration.calibrate import CALIBRATION_FORMAT, CalibrateOptions, Calibration, calibrate
from mvtex.calibration.images import find_images
from mvtex.data.camera import Camera
from mvtex.data.rig import Rig, save_rig
from mvtex.util.checks import as_path, check_instance
from mvtex.util.output import atomic_path, claim_file, claim_output


def write_calibration(calibration: Calibration, rig_file: str | os.PathLike,
                      pictures: str | os.PathLike | None = None) -> dict:
    """Write the rig YAML and, given a `pictures` folder, `calibration.json` there (options,
    per-camera and per-frame numbers, skipped frames), `rig.png` (frusta and board poses)
    and `residuals.png` (per camera, the reprojection residuals over the image). Each is
    written under a temporary name and renamed when complete.

    Returns:
        {"rig": path, "pictures": [paths]}.
    """

    rig_file = Path(rig_file)
    files = []
    if pictures is not None:
        folder = Path(pictures)
        with atomic_path(folder) as tmp:
            tmp.mkdir()
            record = {"format": CALIBRATION_FORMAT, "version": 1, "rig": str(rig_file),
                      "options": {**calibration.options.to_json(), "reference": calibration.reference}
                      if calibration.options else None,
                      **calibration.summary(),
                      "frames": list(calibration.frames),
                      "cameras": {name: {"frames": list(obs.frames), "skipped": list(obs.skipped),
                                         "corners": int(sum(len(d) for d in obs.detections)),
                                         "frame_rms_px": calibration.frame_rms_px(name)}
                                  for name, obs in calibration.observations.items()}}
            (tmp / "calibration.json").write_text(json.dumps(record, indent=2) + "\n")
            plot_rig(calibration.rig, tmp / "rig.png", board=calibration.board,
                     world_from_board=calibration.world_from_board,
                     title=f"{len(calibration.rig)} cameras, {len(calibration.frames)} board poses, "
                           f"RMS {calibration.rms_px:.3f} px")
            plot_residuals(calibration, tmp / "residuals.png")
        files = [str(folder / "calibration.json"), str(folder / "rig.png"), str(folder / "residuals.png")]
    save_rig(calibration.rig, rig_file)
    return {"rig": str(rig_file), "pictures": files}


def calibrate_folder(images: str | os.PathLike, rig_file: str | os.PathLike, options: CalibrateOptions, *,
                     pictures: str | os.PathLike | None = None, progress: bool = True,
                     overwrite: bool = False) -> Calibration:
    """`mvtex calibrate`: find the images, calibrate, write the rig (and, into `pictures`,
    the record and pictures of the calibration). Both outputs follow the writer policy of
    `mvtex.util.output`: an existing rig file is replaced only with `overwrite`, neither
    output may be, hold or lie inside the image folder."""

    images, rig_file = as_path(images, "images"), as_path(rig_file, "rig_file")
    pictures = as_path(pictures, "pictures", optional=True)
    check_instance(options, CalibrateOptions, "options")

    with contextlib.ExitStack() as claims:
        claims.enter_context(claim_file(rig_file, "calibrate", overwrite=overwrite, inputs=[images]))
        if pictures is not None:
            claims.enter_context(claim_output(pictures, "calibrate", overwrite=overwrite, inputs=[images, rig_file]))
        calibration = calibrate(find_images(images), options, progress=progress)
        write_calibration(calibration, rig_file, pictures)
    return calibration


def _frustum(camera: Camera, depth: float) -> np.ndarray:
    """(5,3) world points: the centre and the image corners at `depth` along the axis."""
    W, H = camera.width, camera.height
    corners = np.array([[-0.5, -0.5], [W - 0.5, -0.5], [W - 0.5, H - 0.5], [-0.5, H - 0.5]])
    rays = np.hstack([corners, np.ones((4, 1))]) @ np.linalg.inv(camera.K).T * depth
    return np.vstack([camera.center, (rays - camera.t) @ camera.R])


def plot_rig(rig: Rig, path: str | os.PathLike, *, board: BoardSpec | None = None,
             world_from_board: np.ndarray | None = None, title: str = "") -> None:
    """A 3-D picture of the rig: camera frusta (image top edge in black), names, and the
    board outlines (their x edge thicker).

    Drawn in the cameras' mean axes: right, forward (mean viewing direction) and up (mean
    of the cameras' -y), so a rig looks upright whichever world frame it uses.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: PLC0415 (loaded on use)
    from matplotlib.figure import Figure  # noqa: PLC0415 (loaded on use)

    up = -np.mean([cam.R[1] for cam in rig], axis=0)
    up /= np.linalg.norm(up)
    forward = np.mean([cam.R[2] for cam in rig], axis=0)
    forward -= up * np.dot(forward, up)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    display = np.stack([right, forward, up])

    def show(p):  # world points (..., 3) -> plot coordinates (right, forward, up)
        q = np.asarray(p) @ display.T
        return q[..., 0], q[..., 1], q[..., 2]

    fig = Figure(figsize=(8, 6.5), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="3d")
    centres = np.stack([c.center for c in rig])
    everything = [centres]
    boards = []
    if board is not None and world_from_board is not None and len(world_from_board):
        w, h = board.size_m
        outline = np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0], [0, 0, 0]])
        boards = [outline @ T[:3, :3].T + T[:3, 3] for T in world_from_board]
        everything += boards
    pts = np.vstack(everything)
    scale = max(float(np.ptp(pts, axis=0).max()), 0.1)
    from matplotlib import colormaps  # noqa: PLC0415 (loaded on use)

    colors = colormaps["viridis"](np.linspace(0, 1, max(len(boards), 1)))
    for i, b in enumerate(boards):
        ax.plot(*show(b), color=colors[i], lw=1.0, alpha=0.8)
        ax.plot(*show(b[:2]), color=colors[i], lw=2.2, alpha=0.9)  # the board's x axis edge
    for cam in rig:
        f = _frustum(cam, 0.12 * scale)
        for k in range(1, 5):
            ax.plot(*show(f[[0, k]]), color="tab:red", lw=1.0)
        ax.plot(*show(f[[1, 2, 3, 4, 1]]), color="tab:red", lw=1.4)
        ax.plot(*show(f[[1, 2]]), color="black", lw=2.0)  # image top edge
        ax.text(*show(cam.center + up * 0.03 * scale), cam.name, fontsize=9)
    shown = pts @ display.T
    lo, hi = shown.min(axis=0), shown.max(axis=0)
    mid, half = (lo + hi) / 2, (hi - lo).max() / 2 + 0.05 * scale
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(mid[2] - half, mid[2] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("right (m)")
    ax.set_ylabel("forward (m)")
    ax.set_zlabel("up (m)")
    ax.view_init(elev=22, azim=-62)
    ax.set_title(title or f"{len(rig)} cameras", fontsize=10)
    fig.tight_layout()
    _save_figure(fig, path)


def plot_residuals(calibration: Calibration, path: str | os.PathLike, *, columns: int = 3) -> None:
    """Per camera, each detected corner over the image with its reprojection residual
    (arrow, magnified) coloured by its length in pixels."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: PLC0415 (loaded on use)
    from matplotlib.figure import Figure  # noqa: PLC0415 (loaded on use)

    names = calibration.rig.names
    cols = min(columns, len(names))
    rows = (len(names) + cols - 1) // cols
    fig = Figure(figsize=(4.6 * cols, 3.9 * rows), dpi=100)
    FigureCanvasAgg(fig)
    everything = np.concatenate([np.linalg.norm(r, axis=1) for r in calibration.residuals.values()])
    vmax = max(float(np.percentile(everything, 99)), 1e-3) if everything.size else 1.0
    typical = max(float(np.median(everything)), 1e-3) if everything.size else 1.0
    magnify = float(np.round(0.03 * max(c.width for c in calibration.rig) / typical, -1) or 1.0)
    for i, name in enumerate(names):
        cam = calibration.rig[name]
        ax = fig.add_subplot(rows, cols, i + 1)
        obs = calibration.observations[name]
        pixels = np.concatenate([d.pixels for d in obs.detections])
        r = calibration.residuals[name]
        length = np.linalg.norm(r, axis=1)
        sc = ax.scatter(pixels[:, 0], pixels[:, 1], c=length, cmap="viridis", vmin=0, vmax=vmax, s=3)
        ax.quiver(pixels[:, 0], pixels[:, 1], r[:, 0] * magnify, r[:, 1] * magnify, length, cmap="viridis",
                  angles="xy", scale_units="xy", scale=1, width=0.0025, clim=(0, vmax))
        ax.set_xlim(-0.5, cam.width - 0.5)
        ax.set_ylim(cam.height - 0.5, -0.5)
        ax.set_aspect("equal")
        ax.set_title(f"{name}: {len(obs.frames)} frames, RMS {calibration.camera_rms_px(name):.3f} px", fontsize=9)
        ax.tick_params(labelsize=7)
        fig.colorbar(sc, ax=ax, fraction=0.035, pad=0.02).set_label("residual (px)", fontsize=7)
    fig.suptitle(f"reprojection residuals (arrows x{magnify:.0f})", fontsize=10)
    fig.tight_layout()
    _save_figure(fig, path)


def _save_figure(fig, path: str | os.PathLike) -> None:

    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
