"""An exported map uses the run's configured wall and free thresholds (``[slam.grid]``)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from mazebot.persist.export import three_state
from mazebot.slam.grid import FREE, OCCUPIED, UNKNOWN


def _saved(slam_config: dict[str, object]) -> SimpleNamespace:
    logit = math.log(0.8 / 0.2)  # a cell at 80 %: a wall at the default 0.75, unknown at 0.9
    return SimpleNamespace(meta={"config": {"slam": slam_config}}, log_odds=np.array([[logit, -logit]]))


def test_the_configured_thresholds_decide_what_is_a_wall() -> None:
    assert three_state(_saved({})).tolist() == [[OCCUPIED, FREE]]  # type: ignore[arg-type]
    strict = {"occupied_prob": 0.9, "free_prob": 0.1}
    assert three_state(_saved({"grid": strict})).tolist() == [[UNKNOWN, UNKNOWN]]  # type: ignore[arg-type]


def test_a_run_saved_with_the_flat_keys_keeps_its_thresholds() -> None:
    flat = {"grid_occupied_prob": 0.9, "grid_free_prob": 0.1}
    assert three_state(_saved(flat)).tolist() == [[UNKNOWN, UNKNOWN]]  # type: ignore[arg-type]
