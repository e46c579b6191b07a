"""The RPLidar family: what each model says about itself, the speed it talks at, its scan modes.

One table, the only place these facts live. Where they come from:

* A1M8: GET_INFO model 0x18 (24), firmware 1.29, hardware 7, and the five scan modes
  with their GET_LIDAR_CONF values (Standard 508 us, Express 254 us, Boost and
  Sensitivity 127 us, Stability 201 us, 12 m, answer types 0x81/0x82/0x84) as read
  from a unit and listed in thijses/rplidar, thijs_rplidar.h; 5.5 rev/s (datasheet).
* Serial speeds: Slamtec's rplidar_ros launch files (rplidar_a2m12.launch,
  rplidar_a3.launch 256000, rplidar_c1.launch 460800, rplidar_s2.launch 1000000; A1
  and A2M8 115200 by their datasheets).
* S-series: an S1 reports Standard 0x81 and DenseBoost 0x85 (typical), the dense
  capsules of the time-of-flight heads (public output quoted in a GitHub README).
* The other models' sample rates and ranges are their datasheets' headline figures
  (A2M8 8k, A2M12 16k, A3 16k samples/s; C1 5k; S2 32k; ranges 12, 12, 25, 12, 30 m),
  spread over the same mode names; their GET_INFO model bytes follow the series /
  sub-model nibbles of the A1's 0x18 and are this emulator's, not read from units.
"""

from __future__ import annotations

from dataclasses import dataclass

from mazebot.io import rplidar_protocol as proto
from mazebot.io.rplidar_protocol import ScanModeInfo


@dataclass(frozen=True)
class LidarModel:
    """One RPLidar model as the emulator plays it."""

    key: str  # the name in [sim] lidar_model and `mazebot sim lidar --model`
    name: str  # what the datasheet calls it
    model_id: int  # GET_INFO model byte
    firmware: tuple[int, int]  # major, minor
    hardware: int
    baudrate: int  # the serial speed the unit speaks
    rev_per_s: float  # typical rotation rate
    modes: tuple[ScanModeInfo, ...]
    typical_mode: int  # GET_LIDAR_CONF SCAN_MODE_TYPICAL
    triangulation: bool  # angle offsets from the range (A series) or none (time of flight)

    def mode(self, mode_id: int) -> ScanModeInfo:
        for m in self.modes:
            if m.id == mode_id:
                return m
        raise KeyError(mode_id)

    @property
    def standard_us(self) -> float:
        return self.mode(proto.SCAN_MODE_ID_STANDARD).us_per_sample

    @property
    def express_us(self) -> float:
        """GET_SAMPLERATE's express figure: the legacy express mode, else the typical one."""
        legacy = [m for m in self.modes if m.answer_type == proto.TYPE_EXPRESS]
        return (legacy[0] if legacy else self.mode(self.typical_mode)).us_per_sample


def _triangulation_modes(standard_us: float, max_m: float) -> tuple[ScanModeInfo, ...]:
    """Standard, Express (twice the rate), Boost and Sensitivity (four times), Stability
    (2.5 times), as an A1M8 lists them; the A2/A3 the same at their own rates."""
    return (
        ScanModeInfo(0, "Standard", standard_us, max_m, proto.TYPE_SCAN),
        ScanModeInfo(1, "Express", standard_us / 2, max_m, proto.TYPE_EXPRESS),
        ScanModeInfo(2, "Boost", standard_us / 4, max_m, proto.TYPE_ULTRA),
        ScanModeInfo(3, "Sensitivity", standard_us / 4, max_m, proto.TYPE_ULTRA),
        ScanModeInfo(4, "Stability", round(standard_us / 2.53), max_m, proto.TYPE_ULTRA),
    )


def _dense_modes(standard_us: float, dense_us: float, max_m: float) -> tuple[ScanModeInfo, ...]:
    return (
        ScanModeInfo(0, "Standard", standard_us, max_m, proto.TYPE_SCAN),
        ScanModeInfo(1, "DenseBoost", dense_us, max_m, proto.TYPE_DENSE),
    )


MODELS: dict[str, LidarModel] = {
    m.key: m
    for m in (
        LidarModel("a1", "A1M8", 0x18, (1, 29), 7, 115200, 5.5, _triangulation_modes(508, 12.0), 3, True),
        LidarModel("a2m8", "A2M8", 0x28, (1, 27), 6, 115200, 10.0, _triangulation_modes(500, 12.0), 3, True),
        LidarModel("a2m12", "A2M12", 0x2C, (1, 32), 6, 256000, 10.0, _triangulation_modes(250, 12.0), 3, True),
        LidarModel("a3", "A3M1", 0x31, (1, 29), 6, 256000, 10.0, _triangulation_modes(250, 25.0), 3, True),
        LidarModel("c1", "C1M1", 0x41, (1, 2), 18, 460800, 10.0, _dense_modes(200, 200, 12.0), 1, False),
        LidarModel("s2", "S2M1", 0x71, (1, 2), 18, 1000000, 10.0, _dense_modes(62, 31.25, 30.0), 1, False),
    )
}

#: Model names by GET_INFO model byte, for messages about a device that answered.
NAMES_BY_MODEL_ID = {m.model_id: m.name for m in MODELS.values()}
#: The serial speeds the family speaks, slowest first (what a silent port is tried at).
BAUDRATES = sorted({m.baudrate for m in MODELS.values()})


def model_name(model_id: int) -> str:
    """``A1M8`` for 0x18; the nibbles for a model not in the table."""
    return NAMES_BY_MODEL_ID.get(model_id, f"model {model_id:#04x}")
