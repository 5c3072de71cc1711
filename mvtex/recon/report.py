"""The reconstruction's report against gt: RMSE, reprojection error, strain energies.
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

import numpy as np

from mvtex.data.mesh import edge_strain, edges
from mvtex.recon.geometry import rmse
from mvtex.recon.triangulate import ReconOptions, Reconstruction


def strain_energies(positions: np.ndarray, rest: np.ndarray, faces: np.ndarray) -> dict[str, float]:
    """Compression and extension energies of a mesh against its rest shape.

    With s = len/rest_len - 1 per edge: compression = Σ_{s<0} s² / #edges, extension =
    Σ_{s>0} s² / #edges; also the mean |s|.
    """
    s = edge_strain(positions, rest, edges(faces))
    return {"compression": float(np.sum(np.minimum(s, 0) ** 2) / len(s)),
            "extension": float(np.sum(np.maximum(s, 0) ** 2) / len(s)),
            "mean_abs_strain": float(np.mean(np.abs(s)))}


def reconstruction_report(rec: Reconstruction, gt: np.ndarray, faces: np.ndarray, rest: np.ndarray | None,
                          pose: int, options: ReconOptions = ReconOptions()) -> dict:
    """The JSON report (DESIGN §7) of a reconstruction against the gt positions (n,3)."""
    tri = rec.triangulated
    err = rec.reprojection_error[tri]
    report: dict[str, Any] = {
        "pose": int(pose),
        "num_vertices": int(len(gt)),
        "num_triangulated": int(tri.sum()),
        "rmse_m": {"inferred": rmse(rec.inferred, gt), "reconstructed": rmse(rec.points, gt)},
        "rmse_triangulated_m": {"inferred": rmse(rec.inferred, gt, tri), "reconstructed": rmse(rec.points, gt, tri)},
        "mean_reprojection_error_px": float(np.mean(err)) if err.size else None,
        "rejected": dict(rec.rejected),
        "rejected_observations": dict(rec.rejected_observations),
        "stats": dict(rec.stats),
        "strain_energy": None,
        "smooth": {"enabled": bool(options.smooth)},
    }
    if rest is not None:
        report["strain_energy"] = {k: strain_energies(x, rest, faces) for k, x in
                                   (("gt", gt), ("inferred", rec.inferred), ("reconstructed", rec.points))}
    if rec.unsmoothed is not None:
        report["smooth"].update(
            iterations=int(options.smooth_iterations),
            before={"rmse_m": rmse(rec.unsmoothed, gt), "rmse_triangulated_m": rmse(rec.unsmoothed, gt, tri),
                    "strain_energy": None if rest is None else strain_energies(rec.unsmoothed, rest, faces)})
    report["options"] = asdict(options)
    return report
