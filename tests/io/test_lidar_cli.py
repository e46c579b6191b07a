"""``mazebot lidar info|health|dump|decode``, through argparse with the module's own ``register``."""

from __future__ import annotations

import argparse
import io
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest

from mazebot.errors import HardwareUnavailable, MazebotError, UsageError
from mazebot.io import lidar_cli
from mazebot.io import rplidar_protocol as proto

if TYPE_CHECKING:
    from conftest import PtyLidar


def parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="mazebot")
    sub = parser.add_subparsers(dest="command", required=True)
    lidar_cli.register(sub)
    return parser.parse_args(argv)


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """Like the top-level CLI: a MazebotError becomes one stderr line and its exit code."""
    args = parse(argv)
    try:
        code = args.func(args)
    except MazebotError as exc:
        print(f"mazebot: {exc}", file=sys.stderr)
        code = exc.exit_code
    out, err = capsys.readouterr()
    return code, out, err


def sweep(n: int, seed: int) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    angle = np.rint(np.arange(n) * 0.99 * 64) % (360 * 64) / 64
    dist = np.rint(rng.uniform(150, 8000, n) * 4) / 4
    dist[::17] = 0.0  # no return: still a sample
    quality = rng.integers(0, 64, n)
    start = np.zeros(n, dtype=bool)
    start[1:] = np.diff(angle) < 0
    return angle, dist, quality, start


def json_lines(angle: np.ndarray, dist: np.ndarray, quality: np.ndarray, start: np.ndarray) -> list[dict]:
    return [
        {"angle_deg": float(a), "dist_mm": float(d), "quality": int(q), "start": bool(s)}
        for a, d, q, s in zip(angle, dist, quality, start, strict=True)
    ]


@pytest.mark.parametrize("with_descriptor", [False, True])
def test_decode_returns_exactly_the_valid_samples(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], with_descriptor: bool
) -> None:
    angle, dist, quality, start = sweep(2500, seed=4)
    wire = proto.encode_standard_samples(angle, dist, quality, start)
    rng = np.random.default_rng(12)
    pieces = [proto.SCAN_DESCRIPTOR.encode()] if with_descriptor else [b"\x9f\x13"]  # or mid-stream
    kept: list[int] = []
    garbage = 0 if with_descriptor else 2
    i = 0
    while i < 2500:
        run_len = 12 if i == 0 else int(rng.integers(1, 30))
        pieces.append(wire[5 * i : 5 * (i + run_len)])
        kept.extend(range(i, min(i + run_len, 2500)))
        i += run_len
        junk = rng.integers(0, 256, int(rng.integers(1, 25)), dtype=np.uint8).tobytes()
        pieces.append(junk)
        garbage += len(junk)
    path = tmp_path / "scan.bin"
    path.write_bytes(b"".join(pieces))

    code, out, err = run(["lidar", "decode", str(path)], capsys)

    assert code == 0
    expected = json_lines(angle, dist, quality, start)
    assert [json.loads(line) for line in out.splitlines()] == [expected[k] for k in kept]
    assert err.strip() == f"decoded {len(kept)} samples (standard), dropped {garbage} bytes"


def test_decode_reads_stdin(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    angle, dist, quality, start = sweep(50, seed=1)
    data = proto.encode_standard_samples(angle, dist, quality, start)
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(data)))
    code, out, _ = run(["lidar", "decode", "-"], capsys)
    assert code == 0
    assert [json.loads(line) for line in out.splitlines()] == json_lines(angle, dist, quality, start)


def test_decode_express_is_detected_from_the_descriptor(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    caps = [proto.encode_express_capsule(16.0 * k, np.full(32, 1000.0 + k), start=k == 0) for k in range(4)]
    path = tmp_path / "express.bin"
    path.write_bytes(proto.EXPRESS_DESCRIPTOR.encode() + b"".join(caps))
    code, out, err = run(["lidar", "decode", str(path)], capsys)
    assert code == 0
    rows = [json.loads(line) for line in out.splitlines()]
    assert len(rows) == 3 * 32  # the last capsule has no successor to interpolate to
    assert rows[0] == {"angle_deg": 0.0, "dist_mm": 1000.0, "quality": 1, "start": False}
    assert rows[33]["angle_deg"] == 16.5
    assert "(express)" in err
    # forcing the wrong mode decodes nothing, and says so
    code, out, err = run(["lidar", "decode", "--mode", "standard", str(path)], capsys)
    assert (code, out) == (0, "")
    assert "decoded 0 samples" in err


def test_decode_of_a_missing_file_is_a_usage_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run(["lidar", "decode", str(tmp_path / "nope.bin")], capsys)
    assert code == UsageError.exit_code == 2
    assert err.count("\n") == 1 and "nope.bin" in err


@pytest.mark.parametrize("command", ["info", "health", "dump"])
def test_missing_port_exits_69_with_one_line(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["lidar", command, "--port", "/dev/ttyNOPE_mazebot"] + (["--seconds", "1"] if command == "dump" else [])
    args = parse(argv)
    with pytest.raises(HardwareUnavailable) as err:
        args.func(args)
    assert err.value.exit_code == 69
    code, out, stderr = run(argv, capsys)
    assert code == 69
    assert out == ""
    assert stderr.count("\n") == 1
    assert stderr.startswith("mazebot: lidar serial port /dev/ttyNOPE_mazebot cannot be opened")


def test_missing_port_through_the_real_entry_point() -> None:
    if not Path(lidar_cli.__file__).with_name("..").joinpath("cli.py").resolve().exists():
        pytest.skip("mazebot/cli.py is not there yet")
    proc = subprocess.run(
        [sys.executable, "-m", "mazebot", "lidar", "info", "--port", "/dev/ttyNOPE_mazebot"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 69
    assert proc.stdout == ""
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and "/dev/ttyNOPE_mazebot" in lines[0]


def test_port_and_baud_default_to_the_config(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "config.toml"
    config.write_text('[lidar]\nport = "/dev/ttyFROM_CONFIG"\n', encoding="utf-8")
    code, _, err = run(["lidar", "info", "--config", str(config)], capsys)
    assert code == 69
    assert "/dev/ttyFROM_CONFIG" in err
    args = parse(["lidar", "info", "--config", str(config), "--baud", "57600"])
    cfg = lidar_cli._lidar_config(args)
    assert (cfg.port, cfg.baudrate) == ("/dev/ttyFROM_CONFIG", 57600)


def test_info_and_health_from_a_device(pty_lidar: PtyLidar, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run(["lidar", "info", "--port", pty_lidar.path], capsys)
    assert code == 0
    assert out.splitlines() == [
        "model: A1M8 (0x18)",
        "firmware: 1.29",
        "hardware: 7",
        "serial number: 000102030405060708090A0B0C0D0E0F",
        # this fake has no GET_LIDAR_CONF (firmware before 1.24): the SDK's fallback
        "scan modes:",
        "  0: Standard, 2000 samples/s (500 us), max 12 m, answer type 0x81",
        "  1: Express, 4000 samples/s (250 us), max 12 m, answer type 0x82  (typical)",
    ]
    code, out, _ = run(["lidar", "info", "--json", "--port", pty_lidar.path], capsys)
    got = json.loads(out)
    assert got.pop("typical_scan_mode") == 1 and [m["name"] for m in got.pop("scan_modes")] == ["Standard", "Express"]
    assert got == {
        "model": 24,
        "model_name": "A1M8",
        "firmware": "1.29",
        "hardware": 7,
        "serial_number": "000102030405060708090A0B0C0D0E0F",
    }
    code, out, _ = run(["lidar", "health", "--port", pty_lidar.path], capsys)
    assert (code, out.splitlines()) == (0, ["status: warning", "error code: 0x0102"])
    code, out, _ = run(["lidar", "health", "--json", "--port", pty_lidar.path], capsys)
    assert json.loads(out) == {"status": "warning", "error_code": 0x0102}


def test_dump_writes_the_raw_stream_that_decode_reads(
    pty_lidar: PtyLidar, tmp_path: Path, capsysbinary: pytest.CaptureFixture[bytes]
) -> None:
    config = tmp_path / "config.toml"
    config.write_text("[lidar]\nspin_up_s = 0.05\n", encoding="utf-8")
    args = parse(["lidar", "dump", "--seconds", "0.3", "--port", pty_lidar.path, "--config", str(config)])
    assert args.func(args) == 0
    raw = capsysbinary.readouterr().out
    assert raw.startswith(proto.SCAN_DESCRIPTOR.encode())
    # GET_SAMPLERATE: the standard mode's own sample period, for the time stamps
    assert pty_lidar.requests[:4] == [proto.CMD_STOP, proto.CMD_GET_HEALTH, proto.CMD_GET_SAMPLERATE, proto.CMD_SCAN]
    deadline = time.monotonic() + 2
    while pty_lidar.requests[-1] != proto.CMD_STOP and time.monotonic() < deadline:
        time.sleep(0.01)  # the device thread reads the last request a little later
    assert pty_lidar.requests[-1] == proto.CMD_STOP  # dump stops the scan when done
    decoder = proto.StandardScanDecoder()
    samples = proto.DecodedSamples.concat([decoder.feed(raw), decoder.flush()])
    assert len(samples) > 100
    assert decoder.bytes_dropped == 0
    np.testing.assert_allclose(np.diff(samples.angle_deg) % 360, 1.0)


def test_dump_needs_a_positive_duration(capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run(["lidar", "dump", "--seconds", "0", "--port", "/dev/null"], capsys)
    assert code == 2
    assert "--seconds must be positive" in err


@pytest.mark.parametrize(("kind", "encode", "per_capsule"), [
    ("dense", proto.encode_dense_capsule, 40),
    ("ultra", proto.encode_ultra_capsule, 96),
    ("ultradense", proto.encode_ultra_dense_capsule, 64),
])
def test_decode_reads_every_capsule_kind(
    kind: str, encode: object, per_capsule: int, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    fmt = proto.CAPSULE_FORMATS_BY_NAME[kind]
    caps = b"".join(encode(8.0 * k, np.full(per_capsule, 1000.0 + 7 * k), start=k == 0)  # type: ignore[operator]
                    for k in range(4))
    bare, described = tmp_path / "bare.bin", tmp_path / "described.bin"
    bare.write_bytes(caps)
    described.write_bytes(fmt.descriptor.encode() + caps)
    code, out, err = run(["lidar", "decode", "--mode", kind, str(bare)], capsys)
    assert code == 0 and f"({kind})" in err
    rows = [json.loads(line) for line in out.splitlines()]
    assert len(rows) == 3 * per_capsule
    assert rows[0]["dist_mm"] == pytest.approx(1000.0, abs=2.0)
    code, out2, err = run(["lidar", "decode", str(described)], capsys)  # the descriptor says which
    assert code == 0 and f"({kind})" in err and out2 == out


def test_info_prints_the_scan_modes_of_an_emulated_c1(capsys: pytest.CaptureFixture[str]) -> None:
    proc = subprocess.Popen([sys.executable, "-m", "mazebot", "sim", "lidar", "--model", "c1"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        path = proc.stdout.readline().strip()  # type: ignore[union-attr]
        code, out, _ = run(["lidar", "info", "--port", path, "--baud", "460800"], capsys)
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        proc.stdout.close()  # type: ignore[union-attr]
        proc.stderr.close()  # type: ignore[union-attr]
    assert code == 0
    lines = out.splitlines()
    assert lines[0] == "model: C1M1 (0x41)"
    assert lines[-3:] == [
        "scan modes:",
        "  0: Standard, 5000 samples/s (200 us), max 12 m, answer type 0x81",
        "  1: DenseBoost, 5000 samples/s (200 us), max 12 m, answer type 0x85  (typical)",
    ]
