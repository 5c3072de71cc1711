"""Shipped files are found installed and in a source checkout imported without installing."""

import importlib.util
from importlib import resources as importlib_resources
from pathlib import Path

import pytest

from mvtex.util import resources

CHECKOUT = Path(__file__).resolve().parents[2]


def _checkout_module():
    """mvtex/util/resources.py of this checkout, whether or not mvtex is installed from it."""
    spec = importlib.util.spec_from_file_location("checkout_resources", CHECKOUT / "mvtex" / "util" / "resources.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("folder, name", [("shaders", "ids.vert.glsl"), ("shaders", "raster.frag.glsl"),
                                          ("calib", "stereo.yaml")])
def test_shipped_files_are_found_without_the_installed_packages(monkeypatch, folder, name):
    installed = resources.resource_path(folder, name)
    assert installed.is_file(), installed

    def missing(package):
        raise ModuleNotFoundError(package)

    monkeypatch.setattr(importlib_resources, "files", missing)
    checkout = _checkout_module().resource_path(folder, name)
    assert checkout.is_file(), checkout
    assert checkout.parent.parent == CHECKOUT
    assert checkout.read_bytes() == installed.read_bytes()
