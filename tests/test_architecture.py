"""The module map of docs/architecture.md holds: every module is on it, every import points
down its layers, the functions it names exist, and `import mvtex.cli` loads no heavy library."""

from __future__ import annotations

import ast
import importlib
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "mvtex"
DOC = ROOT / "docs" / "architecture.md"
TOP = {"mvtex", "__main__"}  # above every layer: the lazy public API and `python -m mvtex`


def module_map() -> dict[str, tuple[int, str, int]]:
    """module -> (layer, package, row) from the table of docs/architecture.md."""
    rows = re.findall(r"^\| (\d+) \| `([a-z_/]+)\.py` \|", DOC.read_text(), flags=re.M)
    out = {}
    for row, (layer, path) in enumerate(rows):
        parts = path.split("/")
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = (int(layer), parts[0], row)
    return out


def _module_name(path: Path) -> str:
    parts = [p for p in path.relative_to(PACKAGE).with_suffix("").parts if p != "__init__"]
    return ".".join(parts) if parts else "mvtex"


def _imports(path: Path) -> set[str]:
    """mvtex modules a file imports (`from mvtex.a import b`: module a.b if it is one, else a)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level:
            raise AssertionError(f"{path}: relative import (mvtex imports its modules by absolute name)")
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("mvtex."):
            base = node.module[len("mvtex."):]
            for alias in node.names:
                full = f"{base}.{alias.name}"
                out.add(full if (PACKAGE / (full.replace(".", "/") + ".py")).exists() else base)
        elif isinstance(node, ast.Import):
            out.update(a.name[len("mvtex."):] for a in node.names if a.name.startswith("mvtex."))
    return out


def test_every_module_is_on_the_map_and_imports_point_down():
    table = module_map()
    problems = []
    for path in sorted(PACKAGE.rglob("*.py")):
        name = _module_name(path)
        if name in TOP:
            continue
        if name not in table:
            body = ast.parse(path.read_text()).body
            if path.name == "__init__.py" and all(isinstance(n, ast.Expr) for n in body):
                continue  # a package face: its docstring only
            problems.append(f"{name}: not in docs/architecture.md")
            continue
        layer, package, row = table[name]
        for target in sorted(_imports(path)):
            if target not in table:
                if (PACKAGE / target.replace(".", "/")).is_dir():
                    problems.append(f"{name} imports the package {target}, not a module of it")
                continue
            t_layer, t_package, t_row = table[target]
            if t_package == package:
                if t_row >= row:
                    problems.append(f"{name} imports {target}, listed after it in its package")
            elif t_layer >= layer:
                problems.append(f"{name} (layer {layer}) imports {target} (layer {t_layer})")
    assert not problems, "\n".join(problems)


def test_the_map_lists_only_modules_that_exist():
    missing = [m for m in module_map() if not (PACKAGE / (m.replace(".", "/") + ".py")).exists()
               and not (PACKAGE / m.replace(".", "/") / "__init__.py").exists()]
    assert not missing


def test_the_functions_named_for_each_design_step_exist():
    text = DOC.read_text().split("## Where each step of the algorithm lives", 1)[1].split("\n## ", 1)[0]
    names = re.findall(r"`(mvtex\.[a-z_.]+\.[A-Za-z_]+)`", text)
    assert len(names) > 15
    for dotted in names:
        module, _, attr = dotted.rpartition(".")
        assert hasattr(importlib.import_module(module), attr), dotted


def test_cli_import_loads_no_heavy_library():
    heavy = ["moderngl", "torch", "cv2", "pycolmap", "dask", "skimage", "trimesh", "scipy.sparse.linalg"]
    code = ("import sys, mvtex.cli; mvtex.cli.build_parser(); "
            f"print([m for m in {heavy!r} if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
