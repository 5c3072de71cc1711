"""The options of texture sliding (`SlideOptions`), recorded in every texcoord set."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from mvtex.data.limits import MAX_SUBDIV
from mvtex.util.options import Options, knob


@dataclass(frozen=True)
class SlideOptions(Options):
    """Options of texture sliding; `slide_dataset` records them in texcoords.json.

    Attributes:
        subdiv: levels of midpoint subdivision of the inferred mesh (0..`MAX_SUBDIV`).
        fill: how unassigned vertices are filled: "harmonic" or "fmm" (`mvtex.sliding.fill`).
        max_displacement: unassign vertices with ‖d‖ above this (uv units); None = no limit.
        depth_tolerance: relative tolerance of the vertex depth test: the vertex is hidden
            when some inferred surface hits its ray before (1 - tol) times its distance.
        break_ratio: an edge whose two assigned ends have ‖ΔT_N‖ > break_ratio ‖ΔT_G‖ joins
            geodesically far regions; its end with larger ‖d‖ is unassigned. None: no edge
            breaking (the paper's plain method).
        radius: candidate window half-size in pixels around a vertex's projection (1 = 3x3).
        cross_chart: keep hits on another UV chart than the vertex's own (near a seam the
            vertex then shows the right material, but in the other chart's coordinates, so
            d jumps and triangles mixing both frames interpolate garbage). The default
            unassigns them and fills: d stays a within-chart displacement (what a network
            learns and triangulation inverts).
    """

    subdiv: int = knob(1, "midpoint subdivision levels of the inferred mesh", low=0, high=MAX_SUBDIV)
    fill: Literal["harmonic", "fmm"] = knob("harmonic", "fill of unassigned vertices: harmonic (cotangent "
                                            "Laplace) or fmm (geodesic extension)")
    max_displacement: float | None = knob(None, "unassign vertices whose |d| exceeds this", unit="uv",
                                          low=0, low_open=True)
    depth_tolerance: float = knob(1e-3, "relative tolerance of the vertex depth test", low=0, high=1,
                                  high_open=True)
    break_ratio: float | None = knob(None, "break edges whose |dT_N| exceeds this times their |dT_G|; "
                                     "--no-break-ratio: the paper's plain method", low=1, low_open=True,
                                     metavar="R")
    radius: int = knob(1, "candidate window half-size around a vertex's projection (1 = 3x3)", unit="px",
                       low=0, high=4)
    cross_chart: bool = knob(False, "keep hits on another UV chart than the vertex's own")
