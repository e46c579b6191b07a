"""Count the weak-motor notes and dead-encoder faults of whole simulated runs; keep the wheel traces.

A false "the left motor gives only 30 %" in a healthy run is as bad as a weak motor said
late, and ``results.json`` keeps no events of runs without an injected fault, so this runs
the bench's own runs (``mazebot.bench.runner.run_one``) one after the other and taps every
``SharedState.note``. With ``--trace`` it also keeps, per control tick, what the weak-motor
check is built on (throttles written, wheel speeds measured, the controller's targets and
integrals, the wheel gains published), so a detector can be replayed offline on exactly
what the daemon saw.

Example::

    MAZEBOT_DATA=/work/shared/data nice -n 5 .venv/bin/python bench/motor_notes.py \
        --set 6x6 --set training --set faults --out /tmp/notes --trace

writes ``notes.json`` (per run: the fault injected, its detection, every ``motors`` note)
and, with ``--trace``, ``runNN-NAME.npz``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from mazebot.bench.cli import suite_specs, time_limit_s
from mazebot.bench.runner import RunSpec, run_one
from mazebot.config import load_config
from mazebot.sim.faults import FaultSpec
from mazebot.state import SharedState
from mazebot.tasks import control_task
from mazebot.tasks.health_task import HealthMonitor

#: what a weak-motor note says (other ``motors`` notes: the HAT answering again after I²C errors)
WEAK_NOTE = "motor gives only"
#: what a dead-encoder fault says (``HealthMonitor._check_encoders``): in a healthy run it is a false stop
DEAD_ENCODER = "encoder counted nothing"
#: the columns of a trace, one row per control tick
COLUMNS = (
    "now_s", "stamp_s", "written_l", "written_r", "measured_l", "measured_r", "out_l", "out_r",
    "target_l", "target_r", "integral_l", "integral_r", "gain_l", "gain_r", "fault", "moving",
)


def specs_of(name: str) -> list[RunSpec]:
    """The runs of one set: the 6x6 suite's 10 seeds, the 16 training mazes, the fault suite, or motor-weak."""
    if name == "6x6":
        return suite_specs("6x6", 10, "explore", "virtual")
    if name == "faults":
        return suite_specs("faults", 1, "explore", "virtual")
    if name == "weak":
        return [s for s in suite_specs("faults", 1, "explore", "virtual") if s.faults[0].name == "motor-weak"]
    if name.startswith("weak@"):  # the suite's motor-weak run, injected at other moments: weak@12,20,31
        return [replace(s, faults=(FaultSpec("motor-weak", float(t)),)) for t in name[5:].split(",")
                for s in specs_of("weak")]
    if name == "training":
        folder = Path(os.environ.get("MAZEBOT_DATA", "/work/shared/data")) / "mazes" / "training"
        return [RunSpec(str(p), None, 1, "explore", clock="virtual", max_sim_s=time_limit_s(str(p)))
                for p in sorted(folder.glob("*.txt"))]
    raise SystemExit(f"unknown set {name!r}: 6x6, training, faults or weak")


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--set", action="append", required=True, help="6x6, training, faults, weak or weak@T1,T2,...")
    parser.add_argument("--out", required=True)
    parser.add_argument("--trace", action="store_true", help="keep each control tick's wheel trace")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    notes: list[tuple[float, str, str]] = []
    rows: list[tuple[float, ...]] = []
    real_note, real_tick = SharedState.note, control_task.MotorControl.tick

    def note(self: SharedState, source: str, message: str, time_s: float) -> None:
        notes.append((time_s, source, message))
        real_note(self, source, message, time_s)

    def tick(self: control_task.MotorControl, state: SharedState, now_s: float) -> tuple[float, float]:
        written = state.throttles
        left, right = real_tick(self, state, now_s)
        gains = getattr(state, "wheel_gains", (None, None))
        w = self.wheels
        rows.append((now_s, state.pose_time_s if state.pose_time_s is not None else now_s, *written,
                     *state.wheel_speeds_mps, left, right, *w.targets_mps, w.left.integral, w.right.integral,
                     *(np.nan if g is None else g for g in gains), float(bool(state.faults)),
                     float(state.run_state.moving)))
        return left, right

    checks: list[tuple[float, ...]] = []
    real_check = HealthMonitor.check

    def check(self: HealthMonitor, state: SharedState, now_s: float) -> None:
        checks.append((now_s, *state.throttles, *state.wheel_speeds_mps, float(bool(state.faults))))
        real_check(self, state, now_s)

    SharedState.note = note  # type: ignore[method-assign]
    if args.trace:
        control_task.MotorControl.tick = tick  # type: ignore[method-assign]
        HealthMonitor.check = check  # type: ignore[method-assign]
    config = load_config(None)

    def weak_notes(entry: dict[str, Any]) -> int:
        return sum(WEAK_NOTE in m for _, m in entry["motors_notes"])

    specs = [s for name in args.set for s in specs_of(name)]
    report: list[dict[str, Any]] = []
    for i, spec in enumerate(specs):
        notes.clear()
        rows.clear()
        checks.clear()
        t0 = time.perf_counter()
        metrics, record = run_one(config, spec)
        label = f"run{i:02d}-{spec.name}-seed{spec.seed}" + "".join(f"-{f.name}" for f in spec.faults)
        done = [] if record.faults is None else record.faults.injector.injections
        injections = [{"name": inj.spec.name, "begin_s": inj.begin_s, "end_s": inj.end_s} for inj in done]
        entry = {
            "run": label, "done": metrics["done"], "time_s": metrics["time_s"], "coverage": metrics["coverage"],
            "injections": injections, "faults": metrics["faults"],
            "motors_notes": [(t, m) for t, s, m in notes if s == "motors"],
            "dead_encoder_faults": [(t, m) for t, s, m in notes if s == "encoders" and DEAD_ENCODER in m],
            "wall_s": round(time.perf_counter() - t0, 1),
        }
        report.append(entry)
        if args.trace:
            np.savez_compressed(out / f"{label}.npz", trace=np.asarray(rows, dtype=float), columns=np.array(COLUMNS),
                                checks=np.asarray(checks, dtype=float),
                                injections=np.array([[j["begin_s"] or np.nan, j["end_s"] or np.nan]
                                                     for j in injections]).reshape(-1, 2))
        detected = [(r["fault"], r.get("detected_ms"), r["passed"]) for r in (metrics["faults"] or [])]
        print(f"{label}: done={metrics['done']} weak-motor notes={weak_notes(entry)} "
              f"dead-encoder faults={len(entry['dead_encoder_faults'])} faults={detected} "
              f"wall {entry['wall_s']} s", file=sys.stderr, flush=True)
        (out / "notes.json").write_text(json.dumps(report, indent=1) + "\n")
    healthy = sum(weak_notes(e) for e in report if not e["injections"])
    other = sum(weak_notes(e) for e in report if e["injections"] and "motor-weak" not in e["run"])
    dead = sum(len(e["dead_encoder_faults"]) for e in report if not e["injections"])
    print(f"{len(report)} runs; weak-motor notes in runs without a fault: {healthy}, in runs of other faults: "
          f"{other}; dead-encoder faults in runs without a fault: {dead}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
