"""Write a laser log as another robot would have recorded it (:mod:`mazebot.slam.log_degrade`).

From a CARMEN log with corrected poses and the robot's own odometry (the corrected Radish
logs' ``ODOM`` lines, read back by :func:`mazebot.slam.slam_cli.log_odometry`), one of::

    python bench/degrade_log.py IN OUT                       # rewritten as it is (a check: main's figures to the digit)
    python bench/degrade_log.py IN OUT --beams-every 2       # a 1° laser from a 0.5° one
    python bench/degrade_log.py IN OUT --max-range 4.0       # a Hokuyo URG-04LX (5.6: the UG01)
    python bench/degrade_log.py IN OUT --scans-every 2       # half the scan rate
    python bench/degrade_log.py IN OUT --field-deg 240       # a ROBOTLASER1 of a 240° scanner
    python bench/degrade_log.py IN OUT --wheels 0.01,0.02,0.005,0.002 --seed 1   # worse wheels

then ``mazebot slam run --carmen OUT --out DIR`` (no ``--odom-noise``: the odometry written).
Several options together apply in the order above. Prints one JSON line describing the result.
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np

from mazebot.slam.carmen import one_laser, read_carmen
from mazebot.slam.log_degrade import (
    coarser_beams,
    fewer_scans,
    no_echo_range_m,
    odometry_stream,
    short_range,
    wider_field,
    worse_wheels,
    write_log,
)
from mazebot.slam.odometry_errors import parse_systematic
from mazebot.slam.slam_cli import log_odometry


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("log")
    parser.add_argument("out")
    parser.add_argument("--beams-every", type=int, default=1)
    parser.add_argument("--max-range", type=float, default=None, metavar="M")
    parser.add_argument("--scans-every", type=int, default=1)
    parser.add_argument("--field-deg", type=float, default=None)
    parser.add_argument("--wheels", default=None, metavar="WHEEL,TRACK,BIAS,WALK")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--odom-stream", action="store_true",
                        help="write the log's ODOM readings (its gaps kept), not the odometry in the laser lines")
    args = parser.parse_args()
    log = one_laser(read_carmen(args.log))
    lasers = list(log.lasers)
    odometry = log_odometry(log)
    stream = odometry_stream(log, odometry) if args.odom_stream else []
    code = no_echo_range_m(lasers)
    if args.beams_every > 1:
        lasers = [coarser_beams(r, args.beams_every) for r in lasers]
    if args.max_range is not None:
        lasers = [short_range(r, args.max_range, code) for r in lasers]
    if args.scans_every > 1:
        lasers, odometry = fewer_scans(lasers, odometry, args.scans_every)
    if args.field_deg is not None:
        lasers = [wider_field(r, math.radians(args.field_deg), code) for r in lasers]
    if args.wheels is not None:
        if stream:
            raise SystemExit("--wheels writes the odometry at the scans only, not with --odom-stream")
        odometry = worse_wheels(odometry, parse_systematic(args.wheels), args.seed)
    write_log(args.out, lasers, odometry, stream)
    ranges = np.concatenate([r.range_m for r in lasers])
    print(json.dumps({
        "out": args.out, "scans": len(lasers), "beams": sorted({int(r.range_m.size) for r in lasers}),
        "no_echo_code_m": code, "no_echo_share": round(float(np.mean(ranges >= code)), 4),
        "kinds": sorted({r.kind for r in lasers}),
    }))


if __name__ == "__main__":
    main()
