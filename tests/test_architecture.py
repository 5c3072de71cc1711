"""The module map of docs/architecture.md holds: every import points down the layers, and
`import mvtex.cli` loads no heavy library."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "mvtex"

# docs/architecture.md, in order: a module may import modules of lower layers and modules
# listed before it in its own layer.
LAYERS = [
    ["errors", "io", "resources", "parallel", "mesh"],
    ["camera", "dataset", "texcoords"],
    ["geometry", "ply", "raster", "extrapolate", "hitsearch", "skirt", "synth"],
    ["colmap", "viz", "sliding", "board"],
    ["locate", "calibrate"],
    ["recon", "rigs", "slide_jobs", "metrics", "render", "tsnn.atlas", "tsnn.geometry", "tsnn.gp", "tsnn.model", "tsnn.train", "tsnn.predict",
     "tsnn", "bench"],
    ["export", "views", "viewpath", "preview", "report"],
    ["demo", "cli", "__main__"],
]
# `triangulate_pose` (the command's library call) writes its output directory through export.
ALLOWED_UPWARD = {("recon", "export")}


def _rank() -> dict[str, tuple[int, int]]:
    return {name: (layer, i) for layer, names in enumerate(LAYERS) for i, name in enumerate(names)}


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE).with_suffix("")
    parts = [p for p in rel.parts if p != "__init__"]
    return ".".join(parts) if parts else "mvtex"


def _imports(path: Path, name: str) -> set[str]:
    """mvtex modules imported by a file (relative imports resolved)."""
    package = name.split(".")[:-1] if path.name != "__init__.py" else name.split(".")
    if name == "mvtex":
        package = []
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level:
            base = package[:len(package) - (node.level - 1)] if node.level > 1 else package
            if node.module:
                out.add(".".join(base + node.module.split(".")))
            else:
                for alias in node.names:
                    out.add(".".join(base + [alias.name]))
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("mvtex."):
            out.add(node.module[len("mvtex."):])
        elif isinstance(node, ast.Import):
            out.update(a.name[len("mvtex."):] for a in node.names if a.name.startswith("mvtex."))
    return out


def test_every_module_is_on_the_map_and_imports_point_down():
    rank = _rank()
    problems = []
    for path in sorted(PACKAGE.rglob("*.py")):
        name = _module_name(path)
        if name == "mvtex":
            continue
        if name not in rank:
            problems.append(f"{name}: not in docs/architecture.md (add it to the map and to LAYERS)")
            continue
        for target in sorted(_imports(path, name)):
            if target not in rank:
                # `from . import __version__` and the like: names, not modules.
                if (PACKAGE / target.replace(".", "/")).with_suffix(".py").exists():
                    problems.append(f"{name} imports {target}, which is not on the map")
                continue
            if rank[target] >= rank[name] and (name, target) not in ALLOWED_UPWARD:
                problems.append(f"{name} (layer {rank[name][0]}) imports {target} (layer {rank[target][0]})")
    assert not problems, "\n".join(problems)


def test_cli_import_loads_no_heavy_library():
    heavy = ["moderngl", "torch", "cv2", "pycolmap", "dask", "skimage", "trimesh", "scipy.sparse.linalg"]
    code = ("import sys, mvtex.cli; mvtex.cli.build_parser(); "
            f"print([m for m in {heavy!r} if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
