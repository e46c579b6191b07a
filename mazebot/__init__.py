"""mazebot: a Raspberry Pi robot that maps an unknown maze with a lidar and wheel encoders."""

from __future__ import annotations


def __getattr__(name: str) -> str:
    """``mazebot.__version__``: the installed distribution's version, written once, in
    ``pyproject.toml``; read from its metadata on first use, not at every import
    (https://docs.python.org/3/library/importlib.metadata.html#distribution-versions)."""
    if name == "__version__":
        from importlib.metadata import version

        value = version("mazebot")
        globals()["__version__"] = value
        return value
    raise AttributeError(f"module 'mazebot' has no attribute {name!r}")
