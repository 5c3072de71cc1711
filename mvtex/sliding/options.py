"""The options of texture sliding (`SlideOptions`), recorded in every texcoord set.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

from mvtex.sliding.fill import METHODS
from mvtex.util.checks import check_field_types
from mvtex.util.errors import OptionError

if TYPE_CHECKING:
    pass


@dataclass(frozen=True)
class SlideOptions:
    """Options of texture sliding; `slide_dataset` records them in texcoords.json.

    Attributes:
        subdiv: levels of midpoint subdivision of the inferred mesh (0, 1, 2).
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

    subdiv: int = 1
    fill: str = "harmonic"
    max_displacement: float | None = None
    depth_tolerance: float = 1e-3
    break_ratio: float | None = None
    radius: int = 1
    cross_chart: bool = False

    def __post_init__(self) -> None:
        check_field_types(self)
        if int(self.subdiv) != self.subdiv or not 0 <= self.subdiv <= 4:
            raise OptionError(f"subdiv must be an integer in [0, 4], got {self.subdiv!r}")
        if self.fill not in METHODS:
            raise OptionError(f"fill must be one of {', '.join(METHODS)}, got {self.fill!r}")
        if self.max_displacement is not None and not 0 < self.max_displacement < math.inf:
            raise OptionError(f"max_displacement must be a finite number > 0 or None, got {self.max_displacement!r}")
        if not 0 <= self.depth_tolerance < 1:
            raise OptionError(f"depth_tolerance must be in [0, 1), got {self.depth_tolerance!r}")
        if self.break_ratio is not None and not 1 < self.break_ratio < math.inf:
            raise OptionError(f"break_ratio must be a finite number > 1 or None, got {self.break_ratio!r}")
        if int(self.radius) != self.radius or not 0 <= self.radius <= 4:
            raise OptionError(f"radius must be an integer in [0, 4], got {self.radius!r}")

    def to_json(self) -> dict:
        return asdict(self)
