"""The reconstruction's report against gt: RMSE, reprojection error, strain energies.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Mapping

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


@dataclass(frozen=True)
class ErrorPair:
    """An error of the inferred mesh and of the reconstruction, in metres."""

    inferred: float
    reconstructed: float

    @property
    def ratio(self) -> float:
        """inferred / reconstructed (how many times smaller the reconstruction's error is)."""
        return self.inferred / self.reconstructed if self.reconstructed > 0 else float("inf")

    def to_json(self) -> dict:
        return {"inferred": self.inferred, "reconstructed": self.reconstructed}


@dataclass(frozen=True)
class ReconReport:
    """The reconstruction of one pose against gt (`mvtex triangulate`'s report.json, DESIGN §7).

    Attributes:
        pose, num_vertices, num_triangulated: the pose and its vertex counts.
        rmse_m: RMSE over all vertices; rmse_triangulated_m: over the triangulated ones.
        mean_reprojection_error_px: over the triangulated vertices (None if none).
        rejected: vertices not triangulated, by reason.
        rejected_observations: located observations not used, by reason
            (`mvtex.recon.consensus.OBSERVATION_REASONS`).
        stats: counts of the steps (hypotheses, used observations, the vote's threshold, ...).
        strain_energy: {"gt", "inferred", "reconstructed"} energies against the rest shape
            (None without one).
        smooth: {"enabled"} and, when smoothed, the figures before smoothing.
        options: the `ReconOptions` used, as a dict.
        cameras, texcoords, source, subdiv: the cameras and texcoord set (set by
            `triangulate_pose`).
        original: on a corrected set, the mesh before the correction against gt:
            {"rmse_m": over all vertices, "rmse_triangulated_m": over the triangulated ones}
            (`rmse_m.inferred` is then the corrected mesh's); None on any other dataset.
    """

    pose: int
    num_vertices: int
    num_triangulated: int
    rmse_m: ErrorPair
    rmse_triangulated_m: ErrorPair
    mean_reprojection_error_px: float | None
    rejected: Mapping[str, int]
    rejected_observations: Mapping[str, int]
    stats: Mapping[str, Any]
    strain_energy: Mapping[str, Any] | None
    smooth: Mapping[str, Any]
    options: Mapping[str, Any]
    cameras: tuple[str, ...] | None = None
    texcoords: str | None = None
    source: str | None = None
    subdiv: int | None = None
    original: Mapping[str, float] | None = None

    @property
    def ratio_original(self) -> float | None:
        """On a corrected set, the original mesh's all-vertex RMSE over the reconstruction's."""
        if self.original is None:
            return None
        return ErrorPair(self.original["rmse_m"], self.rmse_m.reconstructed).ratio

    def to_json(self) -> dict:
        """The JSON object of report.json and `mvtex triangulate --json`."""
        out = {"pose": self.pose, "num_vertices": self.num_vertices, "num_triangulated": self.num_triangulated,
               "rmse_m": self.rmse_m.to_json(), "rmse_triangulated_m": self.rmse_triangulated_m.to_json(),
               "mean_reprojection_error_px": self.mean_reprojection_error_px, "rejected": dict(self.rejected),
               "rejected_observations": dict(self.rejected_observations), "stats": dict(self.stats),
               "strain_energy": None if self.strain_energy is None else dict(self.strain_energy),
               "smooth": dict(self.smooth), "options": dict(self.options)}
        if self.original is not None:
            out["original_inferred"] = dict(self.original)
        if self.cameras is not None:
            out.update(cameras=list(self.cameras), texcoords=self.texcoords, source=self.source, subdiv=self.subdiv)
        return out


def reconstruction_report(rec: Reconstruction, gt: np.ndarray, faces: np.ndarray, rest: np.ndarray | None,
                          pose: int, options: ReconOptions = ReconOptions(),
                          original: np.ndarray | None = None) -> ReconReport:
    """The report (DESIGN §7) of a reconstruction against the gt positions (n,3); with
    `original` (n,3), a corrected set's mesh before the correction, its errors too."""
    tri = rec.triangulated
    err = rec.reprojection_error[tri]
    strain = None
    if rest is not None:
        strain = {k: strain_energies(x, rest, faces) for k, x in
                  (("gt", gt), ("inferred", rec.inferred), ("reconstructed", rec.points))}
    smooth: dict[str, Any] = {"enabled": bool(options.smooth)}
    if rec.unsmoothed is not None:
        smooth.update(
            iterations=int(options.smooth_iterations),
            before={"rmse_m": rmse(rec.unsmoothed, gt), "rmse_triangulated_m": rmse(rec.unsmoothed, gt, tri),
                    "strain_energy": None if rest is None else strain_energies(rec.unsmoothed, rest, faces)})
    return ReconReport(
        pose=int(pose), num_vertices=int(len(gt)), num_triangulated=int(tri.sum()),
        rmse_m=ErrorPair(rmse(rec.inferred, gt), rmse(rec.points, gt)),
        rmse_triangulated_m=ErrorPair(rmse(rec.inferred, gt, tri), rmse(rec.points, gt, tri)),
        mean_reprojection_error_px=float(np.mean(err)) if err.size else None,
        rejected=dict(rec.rejected), rejected_observations=dict(rec.rejected_observations), stats=dict(rec.stats),
        strain_energy=strain, smooth=smooth, options=asdict(options),
        original=None if original is None else {"rmse_m": rmse(original, gt),
                                                 "rmse_triangulated_m": rmse(original, gt, tri)})
