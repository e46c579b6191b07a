"""``mazebot lidar info|health|dump|decode``: look at the lidar without running the robot.

``info`` (model, firmware, serial number and the scan modes of GET_LIDAR_CONF) and
``health`` ask the device; ``dump`` records its raw scan stream (the
descriptor included) so it can be replayed, attached to a bug report, or fed to
``decode``, which turns such bytes into one JSON object per sample. ``decode`` needs
no device at all: it reads a file (or stdin) that may start anywhere in a stream.

Each subcommand sets ``args.func`` to a function returning the exit code; errors that
are the user's or the hardware's (a missing port) are raised as ``MazebotError`` for
the top-level CLI to print as one line.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from typing import IO, Any

from mazebot.clock import RealClock
from mazebot.config import LidarConfig, load_config
from mazebot.errors import EXIT_OK, UsageError
from mazebot.io import rplidar_protocol as proto
from mazebot.io.rplidar import SCAN_MODES, RPLidar
from mazebot.io.rplidar_models import model_name

READ_CHUNK = 1 << 16


def register(subparsers: Any) -> None:
    """Add the ``lidar`` command and its subcommands to a top-level parser's subparsers."""
    lidar = subparsers.add_parser("lidar", help="talk to the RPLidar or decode its byte stream")
    sub = lidar.add_subparsers(dest="lidar_command", metavar="{info,health,dump,decode}")
    sub.required = True

    def device_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--port", help="serial port of the lidar (default: [lidar] port of the config)")
        p.add_argument("--baud", type=int, help="serial speed (default: [lidar] baudrate of the config)")
        # SUPPRESS: never overwrite a --config given to the top-level parser
        p.add_argument(
            "--config", default=argparse.SUPPRESS, help="config file (default: the one `mazebot config path` prints)"
        )

    info = sub.add_parser("info", help="model, firmware, hardware and serial number",
                          description="Ask the lidar for its model, firmware and hardware version and serial number.")
    device_options(info)
    info.add_argument("--json", action="store_true", help="print one JSON object")
    info.set_defaults(func=cmd_info)

    health = sub.add_parser("health", help="health status and error code",
                            description="Ask the lidar for its health status (Good, Warning, Error) and error code.")
    device_options(health)
    health.add_argument("--json", action="store_true", help="print one JSON object")
    health.set_defaults(func=cmd_health)

    dump = sub.add_parser("dump", help="write the raw scan byte stream to stdout",
                          description="Start a scan and write its raw bytes to stdout, for bug reports and "
                                      "`mazebot lidar decode`.")
    device_options(dump)
    dump.add_argument("--seconds", type=float, required=True, help="how long to record")
    dump.add_argument("--mode", choices=SCAN_MODES, help="scan mode (default: [lidar] scan_mode of the config)")
    dump.set_defaults(func=cmd_dump)

    decode = sub.add_parser("decode", help="decode a raw scan stream into JSON lines",
                            description="Decode a raw scan capture into one JSON object per sample.")
    decode.add_argument(
        "--mode",
        choices=("standard", *proto.CAPSULE_FORMATS_BY_NAME),
        help="sample format: standard, express (legacy capsules), ultra, dense, ultradense "
        "(default: the kind the descriptor at the start of FILE names, else standard)",
    )
    decode.add_argument("file", metavar="FILE", help="raw scan bytes, '-' for stdin")
    decode.set_defaults(func=cmd_decode)


def _lidar_config(args: argparse.Namespace) -> LidarConfig:
    """The config's [lidar] section with --port/--baud applied."""
    cfg = load_config(getattr(args, "config", None)).lidar
    updates: dict[str, Any] = {}
    if getattr(args, "port", None):
        updates["port"] = args.port
    if getattr(args, "baud", None):
        updates["baudrate"] = args.baud
    return cfg.model_copy(update=updates) if updates else cfg


def _lidar(args: argparse.Namespace) -> RPLidar:
    return RPLidar.from_config(_lidar_config(args), RealClock())


def cmd_info(args: argparse.Namespace) -> int:
    """``mazebot lidar info``: what the device says it is."""

    async def run() -> tuple[proto.DeviceInfo, list[proto.ScanModeInfo], int]:
        async with _lidar(args) as lidar:
            info = await lidar.get_info()
            modes, typical = await lidar.get_scan_modes()
            return info, modes, typical

    info, modes, typical = asyncio.run(run())
    if args.json:
        print(
            json.dumps(
                {
                    "model": info.model,
                    "model_name": model_name(info.model),
                    "firmware": info.firmware_version,
                    "hardware": info.hardware,
                    "serial_number": info.serial_hex,
                    "scan_modes": [
                        {"id": m.id, "name": m.name, "us_per_sample": m.us_per_sample,
                         "max_distance_m": m.max_distance_m, "answer_type": m.answer_type}
                        for m in modes
                    ],
                    "typical_scan_mode": typical,
                }
            )
        )
    else:
        print(f"model: {model_name(info.model)} ({info.model:#04x})")
        print(f"firmware: {info.firmware_version}")
        print(f"hardware: {info.hardware}")
        print(f"serial number: {info.serial_hex}")
        print("scan modes:")
        for m in modes:
            print(f"  {m}{'  (typical)' if m.id == typical else ''}")
    return EXIT_OK


def cmd_health(args: argparse.Namespace) -> int:
    """``mazebot lidar health``: good / warning / error and the device's error code."""

    async def run() -> proto.DeviceHealth:
        async with _lidar(args) as lidar:
            return await lidar.get_health()

    health = asyncio.run(run())
    if args.json:
        print(json.dumps({"status": health.status_name, "error_code": health.error_code}))
    else:
        print(f"status: {health.status_name}")
        print(f"error code: {health.error_code:#06x}")
    return EXIT_OK


def cmd_dump(args: argparse.Namespace, out: IO[bytes] | None = None) -> int:
    """``mazebot lidar dump``: the raw scan stream, descriptor first, for ``--seconds``."""
    if args.seconds <= 0:
        raise UsageError(f"--seconds must be positive, got {args.seconds:g}")
    stream = out if out is not None else sys.stdout.buffer
    clock = RealClock()

    async def run() -> None:
        async with _lidar(args) as lidar:
            stream.write(await lidar.start_scan(args.mode))
            deadline_s = clock.now_s() + args.seconds
            while (remaining_s := deadline_s - clock.now_s()) > 0:
                stream.write(await lidar.read_raw(remaining_s))
            stream.flush()

    asyncio.run(run())
    return EXIT_OK


def cmd_decode(args: argparse.Namespace, out: IO[str] | None = None, err: IO[str] | None = None) -> int:
    """``mazebot lidar decode``: one JSON object per sample; a summary on stderr."""
    out = out if out is not None else sys.stdout
    err = err if err is not None else sys.stderr
    try:
        source: IO[bytes] = sys.stdin.buffer if args.file == "-" else open(args.file, "rb")  # noqa: SIM115
    except OSError as exc:
        raise UsageError(f"cannot read {args.file}: {exc.strerror or exc}") from None
    with source:
        first = source.read(READ_CHUNK)
        mode = args.mode or _mode_of_descriptor(first)
        decoder: proto.StandardScanDecoder | proto.ExpressScanDecoder = (
            proto.StandardScanDecoder() if mode == "standard"
            else proto.ExpressScanDecoder(proto.CAPSULE_FORMATS_BY_NAME[mode])
        )
        chunk = first
        while chunk:
            _print_samples(decoder.feed(chunk), out)
            chunk = source.read(READ_CHUNK)
        _print_samples(decoder.flush(), out)
    out.flush()
    print(
        f"decoded {decoder.samples_decoded} samples ({mode}), dropped {decoder.bytes_dropped} bytes",
        file=err,
    )
    return EXIT_OK


def _mode_of_descriptor(head: bytes) -> str:
    """The sample format a capture's leading scan descriptor names (standard without one)."""
    for fmt in proto.CAPSULE_FORMATS.values():
        if head.startswith(fmt.descriptor.encode()):
            return fmt.name
    return "standard"


def _print_samples(samples: proto.DecodedSamples, out: IO[str]) -> None:
    lines = [
        json.dumps({"angle_deg": a, "dist_mm": d, "quality": q, "start": s})
        for a, d, q, s in zip(
            samples.angle_deg.tolist(),
            samples.dist_mm.tolist(),
            samples.quality.tolist(),
            samples.start.tolist(),
            strict=True,
        )
    ]
    if lines:
        out.write("\n".join(lines) + "\n")
