"""Deliberate misuses of the public API, one per line marked `# misuse`: a type checker must
report each of them, and nothing else (tests/typing/test_typing.py runs mypy on this file).
This file is never imported or run."""

from __future__ import annotations

import mvtex

dataset = mvtex.load_dataset("data/shirt")
rig = mvtex.load_rig("stereo")

mvtex.slide_dataset(dataset, rig, 5, poses=[0], options=mvtex.SlideOptions())  # misuse
mvtex.slide_dataset(dataset, rig, "ts", poses=[0], options=mvtex.ReconOptions())  # misuse
mvtex.SlideOptions(subdiv="1")  # misuse
mvtex.SlideOptions(fill="nearest")  # misuse
mvtex.evaluate(dataset, rig, "ts").ratio_materials  # misuse
mvtex.triangulate_pose(dataset, rig, mvtex.open_texcoords("ts"), "32", "recon")  # misuse
report = mvtex.triangulate_pose(dataset, rig, mvtex.open_texcoords("ts"), 32, "recon")
print(report.num_triangulated + " vertices")  # misuse
mvtex.train(dataset, mvtex.open_texcoords("ts"), "model", camera=3)  # misuse
