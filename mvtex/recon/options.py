"""The options of the reconstruction (`ReconOptions`), recorded in every report.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

from mvtex.util.errors import InputError, OptionError
from mvtex.util.options import Options, knob

# consensus_scale of predicted texcoord sets (`ReconOptions.for_source`).
PREDICTED_CONSENSUS_SCALE = 4.0

# shrink of predicted texcoord sets (`ReconOptions.for_source`): see docs/reconstruction.md.
PREDICTED_SHRINK = 0.2

# shrink of predicted texcoord sets on a corrected set (`ReconOptions.for_source` with a
# prior): κ of the fusion with the corrector's σ (`mvtex.recon.trust.fusion_factors`): the
# point's σ taken as it is. Chosen on the validation poses of both built-in garments, both
# multi-camera rigs (`square4`, `trapezoid12`), 240 and 1,000 training poses (eight cells,
# docs/reconstruction.md, "A corrected set: the prior"): the κ of the largest mean gain
# over the corrector whose 10th-percentile pose loses at most 1 % against it in every cell.
# Fused over corrector per pose, mean of the cells' geometric means / worst cell's 10th
# percentile / worst pose: 1.0073 / 0.969 / 0.844 with 0.2, 1.0060 / 0.990 / 0.915 with 1,
# 1.0024 / 0.999 / 0.972 with 5.
FUSED_SHRINK = 1.0


@dataclass(frozen=True)
class ReconOptions(Options):
    """Options of the reconstruction (the `mvtex triangulate` flags mirror them).

    The observation rules (`max_stretch`, `consensus_px`, `consensus_scale`) were chosen on
    held-out poses of both built-in garments and three rigs (docs/reconstruction.md).

    Attributes:
        max_reprojection_px: an observation whose reprojection error exceeds this is dropped
            (while ≥ 3 remain); a point still above it is rejected ("reprojection").
        max_surface_distance: a point farther than this from the inferred surface is
            rejected ("surface_distance").
        max_stretch: an observation located in a triangle with an edge whose ‖ΔT_N‖ exceeds
            this times its ‖ΔT_G‖ is dropped ("stretched_triangle"): T_N there interpolates
            across a fold edge, where the material jumps inside the triangle. None: keep all.
        consensus_px: inlier threshold (px) of the cameras' vote: per vertex, the pair of
            observations whose point the most other cameras see within this (least summed
            truncated squared error) wins, and only the observations within it of the final
            point are used ("disagreement" for the others); a vertex whose best pair does
            not agree within it is not triangulated.
        consensus_scale: the threshold grows to this many times the pose's median
            reprojection error where that is larger than consensus_px; 0: the fixed
            threshold only. None (the default): by the texcoord set's source
            (`for_source`), 4 for predicted texcoords (source "tsnn"), 0 for the others.
            The fixed threshold rejects a camera whose texcoords are off by a pixel even
            where the others are exact; a grown one keeps more of a noisy set's
            observations (on held-out poses of both garments, gp models on square4, 4
            lowers the all-vertex RMSE by 4-5 % against 0) but also a shifted camera's.
        fill_shape: the shape the harmonic extension of the displacement to untriangulated
            vertices is solved on: "rest" (the dataset's rest shape, else the inferred mesh)
            or "inferred".
        smooth: Taubin-smooth the reconstructed displacement (for noisy inputs, e.g. TSNN).
        smooth_iterations: Taubin passes (each a +lambda and a -mu step).
        uv_resolution: texels per side of the UV lookup buffer.
        depth_tolerance: relative depth slack of the visibility test.
        require_assigned: drop hypotheses in triangles with an unassigned (extrapolated)
            corner, when the texcoord set says which are assigned.
        max_combinations: at most this many hypothesis pairs are tried per vertex.
        refine_iterations: Gauss-Newton steps after the DLT (engine "mvtex", and the vote
            of both engines).
        error_scale_m: the PLY's vertex colours run from blue (0) to red (≥ this);
            comparison.png fits its colour scales to the data (`comparison_scales`).
        strain_scale: kept for scripts that set it; comparison.png fits its strain scale to
            the data.
        engine: who triangulates the tracks: "mvtex" (vectorised DLT + Gauss-Newton, the
            default: faster) or "pycolmap" (COLMAP's multi-view triangulation + points-only
            bundle adjustment); both reach the same least-squares points.
        use_uncertainty: where the texcoord set reports its predictive uncertainty
            (`<camera>/uncertainty.npy`), weight each observation by it in the
            triangulation and derive each point's standard deviation from it (else from
            the cameras' disagreement, `consistency_sigma_px`).
        shrink: κ of the trust in each triangulated point: its displacement from the
            inferred position is multiplied by τ² / (τ² + κ σ²), σ the point's standard
            deviation and τ² the pose's mean squared displacement
            (`mvtex.recon.trust.trust_factors`); a point that is not trusted keeps
            the inferred position and passes no displacement to its neighbours (the
            extension to untriangulated vertices starts from the kept displacements).
            0: every point is taken as it is.
            None (the default): by the texcoord set's source (`for_source`),
            `PREDICTED_SHRINK` for predicted texcoords (source "tsnn"), `FUSED_SHRINK` for
            predicted texcoords on a corrected set, 0 for the others.
        use_prior: on a corrected set (`mvtex correct`; the dataset's
            geometry_uncertainty.npy), take the corrected mesh as a prior with the
            corrector's σ: each triangulated point is fused with it, keeping
            σ_p² / (σ_p² + κσ²) of its displacement (κ = `shrink`; points of exact
            texcoords, κ = 0, are kept whole), and the vertices no camera triangulates get
            the prior plus the fused displacement extended to them (`prior_fill`). False: the
            corrected mesh is treated as any inferred mesh.
        prior_gate: g: with a prior, a point whose displacement δ from it has
            ‖δ‖² > g² (σ_p² + κσ²) is an outlier and the prior stands there (None: no gate).
            2: with κ = 1, a gate of 3 let enough of a garbage field that reports a small
            uncertainty through to move 13 % of tests/recon/test_fusion.py's vertices by
            more than σ_p / 10, 2 keeps it to 0.5 %; on the validation poses of the κ
            study neither rejects a point.
        prior_fill: with a prior, extend the fused displacement harmonically to the
            vertices no camera triangulates, as without one (False: the prior stands there).
            On the validation poses of both built-in garments (`square4`, 240 training
            poses) extending raises the median and the worst pose's ratio (T-shirt 1.795 /
            1.015 -> 1.809 / 1.036, skirt 1.880 / 0.784 -> 1.900 / 0.792).
    """

    max_reprojection_px: float = knob(2.0, "drop observations and reject points above this reprojection error",
                                      unit="px", low=0, low_open=True)
    max_surface_distance: float = knob(0.05, "reject points farther than this from the inferred surface", unit="m",
                                       low=0, low_open=True)
    max_stretch: float | None = knob(1.75, "drop observations located in a triangle with an edge whose texcoords "
                                     "stretch more than this times its material length", low=1, low_open=True,
                                     metavar="R")
    consensus_px: float = knob(0.5, "the cameras' vote: an observation agrees with a point within this", unit="px",
                               low=0, low_open=True)
    consensus_scale: float | None = knob(None, "grow the vote's threshold to this times the pose's median "
                                         "reprojection error", low=0, auto=f"{PREDICTED_CONSENSUS_SCALE:g} for predicted texcoords, 0 for slid ones",
                                         metavar="S")
    fill_shape: Literal["rest", "inferred"] = knob("rest", "the shape the displacement of untriangulated vertices "
                                                  "is extended on")
    smooth: bool = knob(False, "Taubin-smooth the reconstructed displacement (for noisy inputs such as predicted "
                        "texcoords)")
    smooth_iterations: int = knob(10, "Taubin passes of --smooth", low=0, high=1000)
    uv_resolution: int = knob(1024, "texels per side of the UV lookup buffer", low=16, high=8192)
    depth_tolerance: float = knob(0.005, "relative depth slack of the visibility test", low=0, low_open=True)
    require_assigned: bool = knob(True, "drop hypotheses in triangles with an unassigned (filled) corner")
    max_combinations: int = knob(256, "most hypothesis pairs tried per vertex", low=1, high=100000)
    refine_iterations: int = knob(5, "Gauss-Newton steps after the DLT", low=0, high=100)
    error_scale_m: float = knob(0.01, "the PLY's vertex colours run from blue (0) to red (at least this)", unit="m",
                                low=0, low_open=True, flag=False)
    strain_scale: float = knob(0.1, "kept for scripts that set it; comparison.png fits its strain scale to the "
                               "data", low=0, low_open=True, flag=False)
    engine: Literal["mvtex", "pycolmap"] = knob("mvtex", "who triangulates the tracks: mvtex (vectorised DLT + "
                                                "Gauss-Newton, faster) or pycolmap (COLMAP's multi-view "
                                                "triangulation + points-only bundle adjustment); the same points")
    use_uncertainty: bool = knob(True, "weigh observations and trust points by the texcoord set's uncertainty.npy "
                                 "where it has one (off: by the cameras' disagreement)")
    shrink: float | None = knob(None, "trust in each point: keep tau2/(tau2 + K sigma2) of its displacement, sigma "
                                "its standard deviation, tau2 the pose's mean squared displacement; 0 takes every "
                                "point", low=0, metavar="K",
                                auto=f"{PREDICTED_SHRINK:g} for predicted texcoords ({FUSED_SHRINK:g} on a corrected "
                                     "set), 0 for slid ones")
    use_prior: bool = knob(True, "on a corrected set (mvtex correct), fuse each point with the corrected mesh and "
                           "its sigma")
    prior_gate: float | None = knob(2.0, "with the prior, a point farther from it than G times their combined sigma "
                                    "is an outlier and the prior stands there", low=0, low_open=True, metavar="G")
    prior_fill: bool = knob(True, "with the prior, extend the fused displacement to the vertices no camera "
                            "triangulates (off: the prior stands there)")

    def for_source(self, source: str, prior: bool = False) -> "ReconOptions":
        """These options with consensus_scale and shrink decided for a texcoord set of this
        source (`TexcoordSet.source`) where they are None: 4 and `PREDICTED_SHRINK` for
        "tsnn" (`FUSED_SHRINK` with a `prior`, a corrected set fused with, `use_prior`),
        else 0."""
        predicted = source == "tsnn"
        out = self
        if self.consensus_scale is None:
            out = replace(out, consensus_scale=PREDICTED_CONSENSUS_SCALE if predicted else 0.0)
        if self.shrink is None:
            kappa = (FUSED_SHRINK if prior and self.use_prior else PREDICTED_SHRINK) if predicted else 0.0
            out = replace(out, shrink=kappa)
        return out


MAX_OBSERVATIONS = 8_000_000
"""Most (gt vertex, camera) pairs one reconstruction takes: the arrays over them hold about
130 bytes a pair (8 million: about 1 GB, within the 2 GB memory target), and everything
that grows faster (camera pairs, DLT rows) is worked through in blocks
(`mvtex.recon.geometry.TRIANGULATION_BLOCK`). Checked before anything is allocated
(`check_observation_count`); benchmarks/triangulate_memory.py measures it."""


def check_observation_count(num_vertices: int, num_cameras: int, source=None) -> None:
    """Refuse a reconstruction of more (vertex, camera) pairs than `MAX_OBSERVATIONS`.

    Raises:
        InputError: naming `source` (the texcoord set) when given, else OptionError.
    """
    pairs = int(num_vertices) * int(num_cameras)
    if pairs > MAX_OBSERVATIONS:
        problem = (f"{num_vertices} vertices seen by {num_cameras} cameras make {pairs} observations, more than "
                   f"{MAX_OBSERVATIONS} (the memory bound of one reconstruction): triangulate with fewer cameras")
        raise InputError(source, problem) if source is not None else OptionError("texcoords", f"hold {problem}")


MIN_SIGMA_PX = 1e-6
"""The smallest standard deviation (px) a reconstruction gives an observation: an
uncertainty of 0 (legal: an exact observation) weighs as this, far below what float32
texcoords resolve, instead of as an infinite weight no least squares can take."""
