"""Shipped files are found installed and in a source checkout imported without installing."""

from importlib import resources as importlib_resources

import pytest

from mvtex.util import resources


@pytest.mark.parametrize("folder, name", [("shaders", "ids.vert.glsl"), ("shaders", "raster.frag.glsl"),
                                          ("calib", "stereo.yaml")])
def test_shipped_files_are_found_without_the_installed_packages(monkeypatch, folder, name):
    installed = resources.resource_path(folder, name)

    def missing(package):
        raise ModuleNotFoundError(package)

    monkeypatch.setattr(importlib_resources, "files", missing)
    checkout = resources.resource_path(folder, name)
    assert checkout.is_file(), checkout
    assert checkout.read_bytes() == installed.read_bytes()
