"""The phone page (index.html, app.js, style.css, vendor/d3.min.js) as package data.

Installed as ``mazebot.static`` (``pyproject.toml``: ``package-dir``); the web server
finds it with ``importlib.resources.files("mazebot.static")``. No code lives here.
"""
