"""Novel views measured: the uv error (the paper's SqrtMSE) along a path between two cameras (the paper's two-camera
plot) and over a 2×2 array (its four-camera map), for

    baseline     the inferred mesh with T_G (no view information)
    blend        `mvtex.views.synthesizer`, method "blend" (the paper)
    reconstruct  `mvtex.views.synthesizer`, method "reconstruct"
    direct TS    texture sliding computed directly at each novel view with gt (the upper bound)

Every curve is the mean over poses of the per-image SqrtMSE (`mvtex.evaluation.evaluate.evaluate`), on
all pixels and on the pixels where the two meshes show the same UV chart (the metric's
`sqrt_mse_same_chart`: chart-boundary pixels no texcoords can fix dominate the former).
Intermediate texcoord sets are written to a temporary folder and removed.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from mvtex.data.dataset import as_dataset
from mvtex.data.rig import Rig
from mvtex.evaluation.evaluate import evaluate
from mvtex.sliding.dataset import slide_dataset
from mvtex.sliding.options import SlideOptions
from mvtex.util.output import atomic_path
from mvtex.views.cameras import interpolate_camera
from mvtex.views.novel import novel_views
from mvtex.views.synthesizer import ViewOptions

CURVES = ("baseline", "blend", "reconstruct", "direct TS")


_COLORS = {"baseline": "#888888", "blend": "#1f77b4", "reconstruct": "#d62728", "direct TS": "#2ca02c"}
# How the plots name the curves (the JSON keeps CURVES).
LABELS = {"baseline": "inferred (T_G)", "blend": "blend", "reconstruct": "reconstruct",
          "direct TS": "direct TS (slid from gt at the view: the upper bound)"}
UV_AXIS = "uv error (1e-3 uv units)"


def measure_views(dataset, rig: Rig, texcoords, weights: Sequence[Mapping[str, float]], names: Sequence[str], *,
                  poses: Sequence[int] | None = None, methods: Sequence[str] = ("blend", "reconstruct"),
                  direct: bool = True, progress: bool = True) -> dict:
    """SqrtMSE per view for the baseline, each method and direct TS.

    Args:
        dataset: `Dataset` with gt. rig: the array. texcoords: the array's `TexcoordSet`.
        weights, names: the views (as for `mvtex.views.novel.novel_views`).
        poses: dataset poses (default: the texcoord set's).
        methods: view methods to measure. direct: also slide directly at each view (gt).

    Returns:
        {"views": names, "weights": [...], "poses": [...],
         "sqrt_mse": {curve: [per view mean]}, "sqrt_mse_same_chart": {curve: [...]}}
        (values in uv units; curve names from CURVES).
    """

    dataset = as_dataset(dataset)
    dataset.require_gt("measuring views against gt")
    poses = texcoords.poses if poses is None else [int(p) for p in poses]
    cameras = Rig(tuple(interpolate_camera(rig, w, n) for w, n in zip(weights, names)))
    out = {"views": list(names), "weights": [dict(w) for w in weights], "poses": poses,
           "sqrt_mse": {}, "sqrt_mse_same_chart": {}}

    def record(curve: str, result, baseline: bool = False) -> None:
        for key in ("sqrt_mse", "sqrt_mse_same_chart"):
            which = "inferred" if baseline else "texcoords"
            out[key][curve] = [getattr(getattr(result.per_camera[n], key), which).mean for n in names]

    with tempfile.TemporaryDirectory(prefix="mvtex-views-") as tmp:
        for method in methods:
            path = Path(tmp) / method
            novel_views(dataset, rig, texcoords, path, weights, names, poses=poses,
                        options=ViewOptions(method=method), progress=progress)
            result = evaluate(dataset, cameras, path, poses=poses, progress=progress)
            if "baseline" not in out["sqrt_mse"]:
                record("baseline", result, baseline=True)
            record(method, result)
        if direct:
            recorded = texcoords.meta.get("options") if isinstance(texcoords.meta.get("options"), dict) else {}
            known = {k: v for k, v in recorded.items() if k in SlideOptions.__dataclass_fields__}
            known["subdiv"] = texcoords.subdiv
            path = Path(tmp) / "direct"
            slide_dataset(dataset, cameras, path, poses=poses, options=SlideOptions(**known), workers=1,
                          progress=progress)
            result = evaluate(dataset, cameras, path, poses=poses, progress=progress)
            if "baseline" not in out["sqrt_mse"]:
                record("baseline", result, baseline=True)
            record("direct TS", result)
    return out


def plot_path(measured: dict, path: str | os.PathLike, parameter: Sequence[float], *, a: str, b: str,
              title: str = "") -> Path:
    """The two-camera plot: the uv error (all pixels | same-chart pixels) against t from a to b."""
    import matplotlib  # noqa: PLC0415 (loaded on use)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415 (loaded on use)

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), dpi=110)
    for ax, key, label in zip(axes, ("sqrt_mse", "sqrt_mse_same_chart"), ("all pixels", "same-chart pixels")):
        for curve in CURVES:
            if curve in measured[key]:
                ax.plot(parameter, np.asarray(measured[key][curve]) * 1e3, "o-", color=_COLORS[curve], label=LABELS[curve],
                        lw=2 if curve == "reconstruct" else 1.5, ms=4)
        ax.set_xlabel(f"t  (0 = {a}, 1 = {b})")
        ax.set_ylabel(UV_AXIS)
        ax.set_title(label)
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(loc="best", fontsize=8)
    fig.suptitle(title or f"novel views between {a} and {b}, mean over {len(measured['poses'])} poses")
    fig.tight_layout()
    return _save(fig, path)


def plot_grid(measured: dict, path: str | os.PathLike, steps: int, corners: Sequence[str], *,
              key: str = "sqrt_mse_same_chart", title: str = "") -> Path:
    """The four-camera map: one heatmap of the uv error over the steps×steps views per curve."""
    import matplotlib  # noqa: PLC0415 (loaded on use)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415 (loaded on use)

    curves = [c for c in CURVES if c in measured[key] and c != "baseline"]
    values = {c: np.asarray(measured[key][c]).reshape(steps, steps) * 1e3 for c in curves}
    # One colour scale for the methods; the baseline (an order of magnitude above) is quoted.
    vmax = max(float(np.nanmax(v)) for v in values.values())
    fig, axes = plt.subplots(1, len(curves), figsize=(3.1 * len(curves) + 0.8, 3.4), dpi=110)
    axes = np.atleast_1d(axes)
    for ax, curve in zip(axes, curves):
        im = ax.imshow(values[curve], cmap="jet", vmin=0, vmax=vmax, origin="upper")
        for i in range(steps):
            for j in range(steps):
                ax.text(j, i, f"{values[curve][i, j]:.2f}", ha="center", va="center", fontsize=8, color="white")
        ax.set_title(f"{LABELS[curve].replace(': the upper bound', '')}\nmean {np.nanmean(values[curve]):.3f}e-3",
                     fontsize=8)
        ax.set_xticks([0, steps - 1], [corners[0], corners[1]])
        ax.set_yticks([0, steps - 1], [corners[0], corners[2]])
    fig.colorbar(im, ax=list(axes), shrink=0.8, label=UV_AXIS)
    base = measured[key].get("baseline")
    base_text = f"; inferred (T_G) mean {np.mean(base) * 1e3:.2f}e-3" if base is not None else ""
    label = "same-chart pixels" if key == "sqrt_mse_same_chart" else "all pixels"
    fig.suptitle(title or f"{steps}x{steps} views over {', '.join(corners)} ({label}, "
                 f"{len(measured['poses'])} poses{base_text})", fontsize=10)
    return _save(fig, path)


def _save(fig, path: str | os.PathLike) -> Path:
    import matplotlib.pyplot as plt  # noqa: PLC0415 (loaded on use)

    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path


def path_plot(dataset, rig: Rig, texcoords, weights: Sequence[Mapping[str, float]], names: Sequence[str],
              plot: str | os.PathLike, *, poses: Sequence[int] | None = None, progress: bool = True) -> dict:
    """Measure views made by `--between` (two cameras) or `--grid` (four) and draw the
    matching picture into `plot`; returns the measurements (plus "plot")."""
    measured = measure_views(dataset, rig, texcoords, weights, names, poses=poses, progress=progress)
    cams = list(dict.fromkeys(k for w in weights for k in w))
    if len(cams) == 2 and len(weights) > 1:
        plot_path(measured, plot, [w[cams[1]] for w in weights], a=cams[0], b=cams[1])
    elif len(cams) == 4 and int(round(np.sqrt(len(weights)))) ** 2 == len(weights):
        plot_grid(measured, plot, int(round(np.sqrt(len(weights)))), cams)
    else:
        print(f"{plot}: a plot needs --between or --grid views; none written", file=sys.stderr)
        return measured
    measured["plot"] = str(plot)
    return measured
