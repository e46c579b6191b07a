"""The daemon's malloc settings: a fixed mmap threshold for it and the processes it starts, free pages given back."""

from __future__ import annotations

import platform

import numpy as np
import pytest

from mazebot.malloc_tuning import ENV_NAME, MMAP_THRESHOLD_BYTES, fix_mmap_threshold, give_back_free_memory

GLIBC = platform.libc_ver()[0] == "glibc"


def test_the_threshold_goes_to_the_processes_started_later() -> None:
    env: dict[str, str] = {}
    took = fix_mmap_threshold(env)
    assert env == {ENV_NAME: str(MMAP_THRESHOLD_BYTES)}
    assert took is GLIBC


def test_a_threshold_set_by_the_user_is_kept() -> None:
    env = {ENV_NAME: "262144"}
    fix_mmap_threshold(env)
    assert env[ENV_NAME] == "262144"
    assert fix_mmap_threshold({ENV_NAME: "lots"}) is False  # not a number: left to glibc, not applied here


@pytest.mark.skipif(not GLIBC, reason="malloc_trim is glibc's")
def test_free_pages_are_given_back() -> None:
    kept = [np.ones(64) for _ in range(20000)]  # small blocks on the heap ...
    del kept[::2]  # ... half of them freed between the others
    assert isinstance(give_back_free_memory(), bool)
    assert all(float(a[0]) == 1.0 for a in kept)  # live blocks untouched
