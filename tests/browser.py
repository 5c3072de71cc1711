"""Node and headless Chromium for the tests: the Khronos glTF validator and pages opened in
Debian's Chromium through playwright-core (tests/js; `npm ci --prefix tests/js` installs them,
.ci/run does). Tests skip where node, the packages or Chromium are missing; with
MVTEX_REQUIRE_BROWSER=1 (set by .ci/run) a missing package or browser fails them instead."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

JS = Path(__file__).resolve().parent / "js"
NODE = shutil.which("node")
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
REQUIRED = os.environ.get("MVTEX_REQUIRE_BROWSER") == "1"


def _missing(what: str) -> None:
    if REQUIRED:
        pytest.fail(f"{what} (MVTEX_REQUIRE_BROWSER=1)")
    pytest.skip(what)


def need_node_package(name: str) -> None:
    """Skip (or fail, in CI) unless node and tests/js/node_modules/<name> are there."""
    if NODE is None:
        pytest.skip("node is not installed")
    if not (JS / "node_modules" / name).is_dir():
        _missing(f"{name} is not installed: npm ci --prefix {JS}")


def need_chromium() -> None:
    need_node_package("playwright-core")
    if CHROMIUM is None:
        _missing("chromium is not installed (Debian: apt-get install chromium)")


def validate_gltf(path: str | os.PathLike) -> dict:
    """The Khronos glTF-Validator's report of a .glb/.gltf file."""
    need_node_package("gltf-validator")
    out = subprocess.run([NODE, str(JS / "validate.cjs"), str(path)], capture_output=True, text=True, check=False, timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def open_pages(pages: list[dict], tmp_path: Path, timeout: float = 400) -> list[dict]:
    """Open each page spec (see tests/js/browser.mjs) in one headless Chromium; returns, per
    page, its console messages, uncaught errors, <html> attributes and final URL."""
    need_chromium()
    job = tmp_path / "browser-job.json"
    job.write_text(json.dumps({"chromium": CHROMIUM, "pages": pages}))
    try:
        out = subprocess.run([NODE, str(JS / "browser.mjs"), str(job)], capture_output=True, text=True,
                             check=False, timeout=timeout, cwd=JS)
    except subprocess.TimeoutExpired:  # a starved machine, not a broken page
        pytest.skip(f"chromium did not finish within {timeout} s")
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout)


def console_errors(result: dict) -> list[str]:
    """A page's uncaught errors and console errors (warnings, such as SwiftShader's notes on
    reading pixels back, are not errors)."""
    return result["errors"] + [m["text"] for m in result["console"] if m["type"] == "error"]
