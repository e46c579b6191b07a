"""A captured run kept in a pickle, for the analysis tools (``ate_breakdown``, ``map_sharpness``).

``--dump FILE`` keeps the run just made; ``--load FILE`` analyses a kept one instead of running
again (a whole simulated run takes minutes, its analysis seconds).
"""

from __future__ import annotations

import argparse
import pickle
from collections.abc import Callable
from typing import Any


def add_keep_options(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--dump", help="keep the run in this pickle")
    ap.add_argument("--load", help="analyse a kept run instead of running one")


def kept_or_new(args: argparse.Namespace, capture: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    """The run of ``--load``, else ``capture()``'s (kept in ``--dump`` when given)."""
    if args.load:
        with open(args.load, "rb") as f:
            return pickle.load(f)
    run = capture()
    if args.dump:
        with open(args.dump, "wb") as f:
            pickle.dump(run, f)
    return run
