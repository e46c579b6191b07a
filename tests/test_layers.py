"""The product's modules import no private name (``_x``) of another module.

A name with a leading underscore is its module's own business; code in another module
that needs it is a sign the name belongs in a public place (the import layers of
``pyproject.toml``, checked by ``lint-imports``, say which modules may import which).
"""

from __future__ import annotations

import ast
from pathlib import Path

import mazebot

PACKAGE = Path(mazebot.__file__).parent


def _private_imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("mazebot"):
            found += [f"{path.relative_to(PACKAGE.parent)}:{node.lineno}: {node.module}.{a.name}"
                      for a in node.names if a.name.startswith("_") and not a.name.startswith("__")]
    return found


def test_no_module_imports_a_private_name_of_another() -> None:
    found = [line for path in sorted(PACKAGE.rglob("*.py")) for line in _private_imports(path)]
    assert found == []


def test_the_check_finds_a_private_import(tmp_path: Path) -> None:
    source = PACKAGE / "_layers_probe.py"
    try:
        source.write_text("from mazebot.slam.slam import _hidden\n")
        assert _private_imports(source) == ["mazebot/_layers_probe.py:1: mazebot.slam.slam._hidden"]
    finally:
        source.unlink()
