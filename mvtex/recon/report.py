"""The reconstruction's report: what it says without gt (the triangulated share, the
reprojection error, the trust in the points, the displacement from the inferred mesh) and,
where the dataset has gt, the RMSE against it; strain energies against the rest shape.
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
    """An error of the inferred mesh and of the reconstruction, in meters."""

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
    """The reconstruction of one pose (`mvtex triangulate`'s report.json, DESIGN §7).

    Attributes:
        pose, num_vertices, num_triangulated: the pose and its vertex counts.
        rmse_m: RMSE against gt over all vertices; rmse_triangulated_m: over the
            triangulated ones; both None for an inference set (no gt).
        mean_reprojection_error_px: over the triangulated vertices (None if none).
        triangulated_share: num_triangulated / num_vertices.
        mean_trust: the mean trust in the triangulated points, in [0, 1]: the share of its
            displacement each keeps (`mvtex.recon.triangulate.trust_factors`; 1 where every
            point is taken, `shrink` 0); None when none was triangulated.
        displacement_m: {"mean", "max"} distance (m) of the reconstruction from the
            inferred mesh over all vertices: how much it moved the predictor's mesh.
        rejected: vertices not triangulated, by reason.
        rejected_observations: located observations not used, by reason
            (`mvtex.recon.consensus.OBSERVATION_REASONS`).
        stats: counts of the steps (hypotheses, used observations, the vote's threshold, ...).
        strain_energy: {"gt", "inferred", "reconstructed"} energies against the rest shape
            (None without one; "gt" None without gt).
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
    rmse_m: ErrorPair | None
    rmse_triangulated_m: ErrorPair | None
    mean_reprojection_error_px: float | None
    rejected: Mapping[str, int]
    rejected_observations: Mapping[str, int]
    stats: Mapping[str, Any]
    strain_energy: Mapping[str, Any] | None
    smooth: Mapping[str, Any]
    options: Mapping[str, Any]
    triangulated_share: float = 0.0
    mean_trust: float | None = None
    displacement_m: Mapping[str, float] | None = None
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
               "rmse_m": None if self.rmse_m is None else self.rmse_m.to_json(),
               "rmse_triangulated_m": None if self.rmse_triangulated_m is None else self.rmse_triangulated_m.to_json(),
               "mean_reprojection_error_px": self.mean_reprojection_error_px,
               "triangulated_share": self.triangulated_share, "mean_trust": self.mean_trust,
               "displacement_m": None if self.displacement_m is None else dict(self.displacement_m),
               "rejected": dict(self.rejected),
               "rejected_observations": dict(self.rejected_observations), "stats": dict(self.stats),
               "strain_energy": None if self.strain_energy is None else dict(self.strain_energy),
               "smooth": dict(self.smooth), "options": dict(self.options)}
        if self.original is not None:
            out["original_inferred"] = dict(self.original)
        if self.cameras is not None:
            out.update(cameras=list(self.cameras), texcoords=self.texcoords, source=self.source, subdiv=self.subdiv)
        return out


def reconstruction_report(rec: Reconstruction, gt: np.ndarray | None, faces: np.ndarray, rest: np.ndarray | None,
                          pose: int, options: ReconOptions = ReconOptions(),
                          original: np.ndarray | None = None) -> ReconReport:
    """The report (DESIGN §7) of a reconstruction, against the gt positions (n,3) where
    given (None: an inference set; every measure against gt is None); with `original`
    (n,3), a corrected set's mesh before the correction, its errors too."""
    tri = rec.triangulated
    n = len(rec.points)
    err = rec.reprojection_error[tri]
    strain = None
    if rest is not None:
        strain = {k: None if x is None else strain_energies(x, rest, faces) for k, x in
                  (("gt", gt), ("inferred", rec.inferred), ("reconstructed", rec.points))}
    smooth: dict[str, Any] = {"enabled": bool(options.smooth)}
    if rec.unsmoothed is not None:
        smooth.update(
            iterations=int(options.smooth_iterations),
            before={"rmse_m": None if gt is None else rmse(rec.unsmoothed, gt),
                    "rmse_triangulated_m": None if gt is None else rmse(rec.unsmoothed, gt, tri),
                    "strain_energy": None if rest is None else strain_energies(rec.unsmoothed, rest, faces)})
    # A point's trust is the share of its displacement it keeps; without shrink every one keeps all.
    trust = rec.stats.get("mean_trust", 1.0) if options.shrink else 1.0
    moved = np.linalg.norm(rec.points - rec.inferred, axis=1)
    return ReconReport(
        pose=int(pose), num_vertices=int(n), num_triangulated=int(tri.sum()),
        rmse_m=None if gt is None else ErrorPair(rmse(rec.inferred, gt), rmse(rec.points, gt)),
        rmse_triangulated_m=None if gt is None else ErrorPair(rmse(rec.inferred, gt, tri), rmse(rec.points, gt, tri)),
        mean_reprojection_error_px=float(np.mean(err)) if err.size else None,
        triangulated_share=float(tri.sum()) / n if n else 0.0,
        mean_trust=float(trust) if tri.any() else None,
        displacement_m={"mean": float(moved.mean()) if n else 0.0, "max": float(moved.max()) if n else 0.0},
        rejected=dict(rec.rejected), rejected_observations=dict(rec.rejected_observations), stats=dict(rec.stats),
        strain_energy=strain, smooth=smooth, options=asdict(options),
        original=None if original is None or gt is None else {"rmse_m": rmse(original, gt),
                                                              "rmse_triangulated_m": rmse(original, gt, tri)})
