"""The product's modules import no private name (``_x``) of another module.

A name with a leading underscore is its module's own business; code in another module
that needs it is a sign the name belongs in a public place (the import layers of
``pyproject.toml``, checked by ``lint-imports``, say which modules may import which).
"""

from __future__ import annotations

import ast
from collections.abc import Callable
from pathlib import Path

import mazebot

PACKAGE = Path(mazebot.__file__).parent


def _private_imports(path: Path, root: Path = PACKAGE.parent) -> list[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("mazebot"):
            found += [f"{path.relative_to(root)}:{node.lineno}: {node.module}.{a.name}"
                      for a in node.names if a.name.startswith("_") and not a.name.startswith("__")]
    return found


def _in_the_package(check: Callable[[Path], list[str]]) -> list[str]:
    """What ``check`` finds in every module of the package."""
    return [line for path in sorted(PACKAGE.rglob("*.py")) for line in check(path)]


def test_no_module_imports_a_private_name_of_another() -> None:
    assert _in_the_package(_private_imports) == []


def test_no_script_in_bench_or_tools_imports_a_private_name_of_the_package() -> None:
    # bench/slam_replay.py imported the runner's _relative after it had moved: the script broke unseen
    repo = PACKAGE.parent
    scripts = sorted([*(repo / "bench").glob("*.py"), *(repo / "tools").glob("*.py")])
    assert [line for path in scripts for line in _private_imports(path, repo)] == []


def test_the_check_finds_a_private_import(tmp_path: Path) -> None:
    source = tmp_path / "probe.py"
    source.write_text("from mazebot.slam.slam import _hidden\n")
    assert _private_imports(source, tmp_path) == ["probe.py:1: mazebot.slam.slam._hidden"]


#: Private names of other libraries the package reaches on purpose: (module file, expression).
#: Each is the library's own way in, or a simulator reaching into gpiozero's mock pins.
FOREIGN_PRIVATE = {
    "argparse._SubParsersAction",  # the type add_subparsers() returns; argparse has no public name for it
    "os._exit",  # how a forked worker leaves without running its parent's exit handlers
    "parts._replace",  # a namedtuple's documented method (the underscore keeps it off the field names)
    "pin_a._state",  # gpiozero's MockPin: the simulator drives the encoder pins as its tests do
    "pin._change_state",
    "handle._callback",  # asyncio's Handle: the bench names the callbacks the loop ran
    # multiprocessing's fork server: mazebot.fork_server registers one forked from the daemon in the
    # fields ensure_running() itself sets (checked present before use; multiprocessing has no public way)
    "forkserver._forkserver",
    "server._lock",
    "server._preload_modules",
    "server._forkserver_address",
    "server._forkserver_alive_fd",
    "server._forkserver_pid",
}


def _private_reaches(path: Path, root: Path = PACKAGE.parent) -> list[str]:
    """``x._name`` in ``path``, ``x`` not ``self``/``cls``/``super()``, where the module does not define ``_name``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    own: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            own.add(node.name)
        elif (isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store)
              and isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")):
            own.add(node.attr)  # self._x = ...: an attribute of this module's own class
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            own.add(node.id)  # class-level _x = ..., or a module-level one
    found = []
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")):
            continue
        owner = node.value
        if isinstance(owner, ast.Name) and owner.id in ("self", "cls"):
            continue
        if isinstance(owner, ast.Call) and isinstance(owner.func, ast.Name) and owner.func.id == "super":
            continue  # a subclass extending its base's hook
        text = ast.unparse(node)
        if node.attr in own or text in FOREIGN_PRIVATE:
            continue
        found.append(f"{path.relative_to(root)}:{node.lineno}: {text}")
    return found


def test_no_module_reaches_into_another_modules_private_attributes() -> None:
    # a saved grid was rebuilt by writing OccupancyGrid's private fields from persist/ (now OccupancyGrid.holding)
    assert _in_the_package(_private_reaches) == []


def test_the_check_finds_a_reach_into_another_modules_private_attribute(tmp_path: Path) -> None:
    source = tmp_path / "probe.py"
    source.write_text(
        "class Mine:\n"
        "    def __init__(self, grid):\n"
        "        self._mine = 1\n"
        "        grid._origin_cells = (0, 0)\n"
        "        other = Mine(grid)\n"
        "        other._mine += 1\n"
    )
    assert _private_reaches(source, tmp_path) == ["probe.py:4: grid._origin_cells"]


#: The modules that may import the simulator or the benchmark: the harness itself and the
#: commands that choose between the robot's devices and the simulator's.
HARNESS_AND_COMMANDS = {
    "mazebot.sim", "mazebot.bench", "mazebot.__main__", "mazebot.__init__", "mazebot.cli", "mazebot.completion_cli",
    "mazebot.run_cli", "mazebot.doctor_cli", "mazebot.calibration_cli", "mazebot.config_cli",
}


def test_every_product_module_is_under_the_contract_that_keeps_the_harness_out() -> None:
    import tomllib

    pyproject = tomllib.loads((PACKAGE.parent / "pyproject.toml").read_text())
    contract = next(c for c in pyproject["tool"]["importlinter"]["contracts"] if c["type"] == "forbidden")
    assert set(contract["forbidden_modules"]) == {"mazebot.sim", "mazebot.bench"}
    top = {f"mazebot.{p.stem}" for p in PACKAGE.glob("*.py")} | {
        f"mazebot.{p.name}" for p in PACKAGE.iterdir() if (p / "__init__.py").exists()
    }
    uncovered = sorted(top - set(contract["source_modules"]) - HARNESS_AND_COMMANDS)
    assert uncovered == [], f"add these to the forbidden contract's source_modules in pyproject.toml: {uncovered}"
