"""One atomic write for every file mazebot saves: the old file or the new one, never a mix."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from mazebot import files
from mazebot.files import write_atomic


def test_a_file_is_replaced_whole_and_its_folder_created(tmp_path: Path) -> None:
    target = tmp_path / "run" / "map.pgm"
    assert write_atomic(target, b"first") == target
    write_atomic(target, b"second")
    assert target.read_bytes() == b"second"
    assert [p.name for p in target.parent.iterdir()] == ["map.pgm"]  # no temporary file left


def test_a_failed_write_leaves_the_old_file_and_no_temporary_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    target = tmp_path / "meta.json"
    write_atomic(target, b"old")

    def full_disk(src: str, dst: str) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(files.os, "replace", full_disk)
    with pytest.raises(OSError, match="No space"):
        write_atomic(target, b"new")
    assert target.read_bytes() == b"old"
    assert os.listdir(tmp_path) == ["meta.json"]


def test_a_file_the_user_named_is_not_given_a_folder(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        write_atomic(tmp_path / "nope" / "out.g2o", b"x", create_folder=False)
    assert not (tmp_path / "nope").exists()


def test_the_savers_share_it() -> None:
    from mazebot.persist import runs
    from mazebot.slam import g2o, map_export

    assert runs.write_atomic is write_atomic
    assert map_export.write_atomic is write_atomic and g2o.write_atomic is write_atomic
    from mazebot.bench import png, report

    assert png.write_atomic is write_atomic and report.files.write_atomic is write_atomic
