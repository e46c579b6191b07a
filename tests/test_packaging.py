"""What ``pip install`` ships: every package of the tree, and the phone page as package data.

The wheel itself, installed outside the checkout (a fresh venv, and ``pip install --user``
into a scratch home) and serving the page, is checked by ``tools/check-install.sh`` in CI.
"""

from __future__ import annotations

import importlib.resources
import re
import tomllib
from pathlib import Path

from mazebot.web.app import find_static_dir

REPO = Path(__file__).resolve().parents[1]


def test_every_package_of_the_tree_and_the_page_are_listed_in_pyproject() -> None:
    tool = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    tree = {".".join(p.parent.relative_to(REPO).parts) for p in (REPO / "mazebot").rglob("__init__.py")}
    assert sorted(tool["packages"]) == sorted(tree | {"mazebot.static"})
    assert tool["package-dir"] == {"mazebot.static": "static"}


def test_the_page_is_the_package_data_mazebot_static_with_every_asset_it_references() -> None:
    folder = find_static_dir()
    assert folder == importlib.resources.files("mazebot.static")
    assert folder.resolve() == (REPO / "static").resolve()  # this editable install maps it to the checkout
    page = (folder / "index.html").read_text()
    assets = re.findall(r'(?:src|href)="/static/([^"]+)"', page)
    assert {"app.js", "style.css", "vendor/d3.min.js"} <= set(assets)
    shipped = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    patterns = shipped["mazebot.static"]
    for asset in assets:
        assert (folder / asset).is_file(), asset
        assert any(Path(asset).match(p) for p in patterns), f"{asset} is not in package-data {patterns}"
