"""``make data`` (tools/fetch_data.py): files land where the tests look, SHA-256 checked, or it says what is missing."""

from __future__ import annotations

import hashlib
import importlib.util
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("fetch_data", REPO / "tools" / "fetch_data.py")
assert spec is not None and spec.loader is not None
fetch_data = importlib.util.module_from_spec(spec)
spec.loader.exec_module(fetch_data)


def _manifest(tmp_path: Path, files: dict[str, bytes], urls: dict[str, str] | None = None) -> Path:
    origin = tmp_path / "origin"
    rows = []
    for name, body in files.items():
        (origin / name).parent.mkdir(parents=True, exist_ok=True)
        (origin / name).write_bytes(body)
        url = (urls or {}).get(name, (origin / name).as_uri())
        rows.append(f"{name}\t{hashlib.sha256(body).hexdigest()}\t{len(body)}\t{url}")
    manifest = tmp_path / "manifest.tsv"
    manifest.write_text("# header\n" + "\n".join(rows) + "\n")
    return manifest


def test_files_are_fetched_into_the_data_folder_and_kept_when_intact(tmp_path: Path) -> None:
    manifest = _manifest(tmp_path, {"mazes/classic/a.txt": b"o---o\n", "carmen/x.log.gz": b"\x1f\x8b\x00"})
    data = tmp_path / "data"
    assert fetch_data.main(["--data", str(data), "--manifest", str(manifest)]) == 0
    assert (data / "mazes/classic/a.txt").read_bytes() == b"o---o\n"
    (tmp_path / "origin" / "mazes/classic/a.txt").unlink()  # intact files are not fetched again
    assert fetch_data.main(["--data", str(data), "--manifest", str(manifest), "--check"]) == 0
    assert fetch_data.main(["--data", str(data), "--manifest", str(manifest)]) == 0


def test_a_changed_origin_or_no_network_is_named_with_where_to_get_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    manifest = _manifest(tmp_path, {"a.txt": b"one", "b.txt": b"two"},
                         urls={"b.txt": "http://127.0.0.1:9/b.txt"})  # the discard port: nothing answers
    (tmp_path / "origin" / "a.txt").write_bytes(b"changed upstream")
    data = tmp_path / "data"
    assert fetch_data.main(["--data", str(data), "--manifest", str(manifest)]) == 1
    err = capsys.readouterr().err
    assert "2 of 2 files missing or wrong" in err
    assert "a.txt: the origin's file changed" in err and "b.txt: cannot download" in err
    assert "http://127.0.0.1:9/b.txt" in err and "MAZEBOT_DATA" in err
    assert not (data / "a.txt").exists()  # a file that fails its SHA-256 is never kept


def test_the_manifest_covers_every_file_the_tests_use_with_an_origin() -> None:
    entries = fetch_data.read_manifest()
    paths = {e.path for e in entries}
    for needed in ("carmen/intel.gfs.log", "posegraphs/input_M3500_g2o.g2o", "posegraphs/input_MITb_g2o.g2o"):
        assert needed in paths
    assert sum(p.startswith("mazes/classic/") for p in paths) == 66
    assert sum(p.startswith("mazes/training/") for p in paths) == 16
    assert all(e.url.startswith("https://") and len(e.sha256) == 64 for e in entries)
