"""The options of the reconstruction (`ReconOptions`), recorded in every report.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from mvtex.util.checks import check_field_types
from mvtex.util.errors import OptionError

# Triangulation engines of `ReconOptions.engine`.
ENGINES = ("mvtex", "pycolmap")

# consensus_scale of predicted texcoord sets (`ReconOptions.for_source`).
PREDICTED_CONSENSUS_SCALE = 4.0

# shrink of predicted texcoord sets (`ReconOptions.for_source`): see docs/reconstruction.md.
PREDICTED_SHRINK = 0.2

# shrink of predicted texcoord sets on a corrected set (`ReconOptions.for_source` with a
# prior): κ of the fusion with the corrector's σ (`mvtex.recon.trust.fusion_factors`),
# chosen on validation poses of both built-in garments (docs/reconstruction.md): with
# `prior_fill`, 0.2 gives the best median on both (T-shirt 1.81, skirt 1.90 on `square4`,
# 240 training poses; 0.5: 1.80, 1.88) and the worst poses within 0.003 of 0.5's.
FUSED_SHRINK = 0.2

# Shapes the harmonic fill of `ReconOptions.fill_shape` can be solved on.
FILL_SHAPES = ("rest", "inferred")


@dataclass(frozen=True)
class ReconOptions:
    """Options of the reconstruction (the `mvtex triangulate` flags mirror them).

    The observation rules (`max_stretch`, `consensus_px`, `consensus_scale`) were chosen on
    held-out poses of both built-in garments and three rigs (docs/reconstruction.md).

    Attributes:
        max_reprojection_px: an observation whose reprojection error exceeds this is dropped
            (while ≥ 3 remain); a point still above it is rejected ("reprojection").
        max_surface_distance_m: a point farther than this from the inferred surface is
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
        prior_fill: with a prior, extend the fused displacement harmonically to the
            vertices no camera triangulates, as without one (False: the prior stands there).
            On the validation poses of both built-in garments (`square4`, 240 training
            poses) extending raises the median and the worst pose's ratio (T-shirt 1.795 /
            1.015 -> 1.809 / 1.036, skirt 1.880 / 0.784 -> 1.900 / 0.792).
    """

    max_reprojection_px: float = 2.0
    max_surface_distance_m: float = 0.05
    max_stretch: float | None = 1.75
    consensus_px: float = 0.5
    consensus_scale: float | None = None
    fill_shape: str = "rest"
    smooth: bool = False
    smooth_iterations: int = 10
    uv_resolution: int = 1024
    depth_tolerance: float = 0.005
    require_assigned: bool = True
    max_combinations: int = 256
    refine_iterations: int = 5
    error_scale_m: float = 0.01
    strain_scale: float = 0.1
    engine: str = "mvtex"
    use_uncertainty: bool = True
    shrink: float | None = None
    use_prior: bool = True
    prior_gate: float | None = 3.0
    prior_fill: bool = True

    def __post_init__(self) -> None:
        check_field_types(self)
        positive = {"max_reprojection_px": self.max_reprojection_px,
                    "max_surface_distance_m": self.max_surface_distance_m, "consensus_px": self.consensus_px,
                    "depth_tolerance": self.depth_tolerance, "error_scale_m": self.error_scale_m,
                    "strain_scale": self.strain_scale}
        for name, value in positive.items():
            if not value > 0 or value == float("inf"):
                raise OptionError(f"{name} must be a positive finite number, got {value!r}")
        if self.max_stretch is not None and not 1 < self.max_stretch < float("inf"):
            raise OptionError(f"max_stretch must be > 1 and finite, or None, got {self.max_stretch!r}")
        if self.consensus_scale is not None and not 0 <= self.consensus_scale < float("inf"):
            raise OptionError(f"consensus_scale must be ≥ 0 and finite, or None, got {self.consensus_scale!r}")
        if self.shrink is not None and not 0 <= self.shrink < float("inf"):
            raise OptionError(f"shrink must be ≥ 0 and finite, or None, got {self.shrink!r}")
        if self.prior_gate is not None and not 0 < self.prior_gate < float("inf"):
            raise OptionError(f"prior_gate must be > 0 and finite, or None, got {self.prior_gate!r}")
        if self.fill_shape not in FILL_SHAPES:
            raise OptionError(f"fill_shape must be one of {', '.join(FILL_SHAPES)}, got {self.fill_shape!r}")
        for name, value, low, high in (("smooth_iterations", self.smooth_iterations, 0, 1000),
                                       ("uv_resolution", self.uv_resolution, 16, 8192),
                                       ("max_combinations", self.max_combinations, 1, 100000),
                                       ("refine_iterations", self.refine_iterations, 0, 100)):
            if int(value) != value or not low <= value <= high:
                raise OptionError(f"{name} must be an integer in [{low}, {high}], got {value!r}")
        if self.engine not in ENGINES:
            raise OptionError(f"engine must be one of {', '.join(ENGINES)}, got {self.engine!r}")

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
