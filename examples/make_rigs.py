"""Make the three example rigs shipped in calib/ (how to build a rig of your own).

    python examples/make_rigs.py calib/

Every camera looks at the origin from about 2.2 m, 512x512 pixels, world y up.
"""

import sys
from pathlib import Path

import numpy as np

from mvtex.data.camera import Camera, look_at
from mvtex.data.rig import Rig, save_rig

SIZE, FOCAL, DISTANCE = 512, 1150.0, 2.2


def on_circle(name: str, azimuth_deg: float, height: float) -> Camera:
    a = np.radians(azimuth_deg)
    r = np.sqrt(DISTANCE**2 - height**2)
    center = (r * np.sin(a), height, r * np.cos(a))
    return look_at(name, center, (0, 0, 0), width=SIZE, height=SIZE, focal=FOCAL)


def rigs() -> dict[str, Rig]:
    stereo = Rig((on_circle("left", -15, 0.0), on_circle("right", 15, 0.0)))
    half = 0.5  # a 1 m square facing the garment
    square = Rig(tuple(look_at(n, (x, y, DISTANCE), (0, 0, 0), width=SIZE, height=SIZE, focal=FOCAL)
                       for n, x, y in (("tl", -half, half), ("tr", half, half), ("bl", -half, -half), ("br", half, -half))))
    rows = ((-0.6, np.linspace(-50, 50, 5)), (0.0, np.linspace(-36, 36, 4)), (0.6, np.linspace(-24, 24, 3)))
    cams, k = [], 0
    for height, azimuths in rows:
        for az in azimuths:
            cams.append(on_circle(f"cam{k:02d}", az, height))
            k += 1
    return {"stereo": stereo, "square4": square, "trapezoid12": Rig(tuple(cams))}


if __name__ == "__main__":
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "calib")
    for name, rig in rigs().items():
        save_rig(rig, out / f"{name}.yaml")
        print(out / f"{name}.yaml", len(rig), "cameras")
