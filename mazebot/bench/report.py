"""results.json, report.md and the figures of a benchmark run."""

from __future__ import annotations

import json
import statistics
from pathlib import Path
from typing import Any

import numpy as np

from mazebot import files
from mazebot.bench.png import Canvas, write_png
from mazebot.bench.runner import RunRecord
from mazebot.sim.backend import simulated_robot
from mazebot.sim.raster import true_occupancy

#: Keys aggregated in the summary (median over runs, ignoring nulls).
SUMMARY_KEYS = (
    "time_s", "wall_s", "realtime_factor", "path_m", "avg_speed_mps", "coverage", "collisions", "revisits",
    "revisits_dfs",
    "ate_rms_m", "ate_max_m", "heading_rms_deg", "ate_rms_turned_back_m", "uncovered_occupied", "uncovered_unknown",
    "map_f1", "scan_ms_p50", "scan_ms_p99", "control_jitter_ms_p99", "cpu_percent", "rss_mb", "loop_closures",
)


def summarize(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Median of each metric over the runs; null where no run has it."""
    out: dict[str, Any] = {"runs": len(runs), "done": sum(1 for r in runs if r["done"])}
    for key in SUMMARY_KEYS:
        values = [r[key] for r in runs if r.get(key) is not None]
        out[f"{key}_median"] = round(statistics.median(values), 4) if values else None
    out["collisions_total"] = sum(r["collisions"] for r in runs)
    out["false_loop_closures_total"] = sum(r.get("false_loop_closures") or 0 for r in runs)
    return out


def write_atomic(path: Path, text: str) -> None:
    """A report file written atomically (:func:`mazebot.files.write_atomic`), as UTF-8 text."""
    files.write_atomic(path, text.encode("utf-8"))


def write_partial(out_dir: Path, metrics: list[dict[str, Any]], command: str, planned: int) -> None:
    """results.json of the runs finished so far (``"partial": true``); the full report replaces it."""
    results = {"command": command, "partial": True, "planned_runs": planned, "runs": metrics,
               "summary": summarize(metrics)}
    write_atomic(out_dir / "results.json", json.dumps(results, indent=2) + "\n")


def trajectory_figure(record: RunRecord, path: Path) -> None:
    """True walls (grey), true trajectory (blue), estimated trajectory (red), in world frame."""
    assert record.hardware is not None
    world = simulated_robot(record.hardware).world
    canvas = Canvas(world.bounds_m, pixels_per_m=400)
    occ, origin = true_occupancy(world, 0.01)
    canvas.paint_mask(occ, origin, 0.01, (150, 150, 150))
    truth = np.asarray(record.true_poses).reshape(-1, 3)
    est = np.asarray(record.est_poses).reshape(-1, 3)
    if len(truth):
        x0, y0, t0 = truth[0]
        c, s = np.cos(t0), np.sin(t0)
        est_world = np.column_stack([x0 + c * est[:, 0] - s * est[:, 1], y0 + s * est[:, 0] + c * est[:, 1]])
        canvas.polyline(truth[:, :2], (40, 90, 220), width_px=2)
        canvas.polyline(est_world, (220, 40, 40), width_px=1)
    write_png(path, canvas.rgb)


def map_figure(record: RunRecord, path: Path) -> bool:
    """SLAM's map in the world frame over the true walls; False (no file) without a map.

    True walls light red, cells the map knows free light blue-grey, its occupied cells
    black; the estimated map is placed with the true start pose (the map frame).
    """
    assert record.hardware is not None and record.state is not None
    grid = record.state.map
    if grid is None or grid.shape[0] == 0:
        return False
    world = simulated_robot(record.hardware).world
    truth = np.asarray(record.true_poses).reshape(-1, 3)
    start = truth[0] if len(truth) else np.asarray(world.start_pose, dtype=float)
    canvas = Canvas(world.bounds_m, pixels_per_m=200)
    occ, origin = true_occupancy(world, 0.01)
    canvas.paint_mask(occ, origin, 0.01, (250, 170, 170))
    c, s = np.cos(start[2]), np.sin(start[2])

    def paint(mask: np.ndarray, color: tuple[int, int, int]) -> None:
        rows, cols = np.nonzero(mask)
        xy = grid.to_world(rows, cols)
        world_xy = np.column_stack((start[0] + c * xy[:, 0] - s * xy[:, 1], start[1] + s * xy[:, 0] + c * xy[:, 1]))
        r, q = canvas.to_px(world_xy)
        half = max(1, round(grid.resolution_m * canvas.scale / 2))
        for dr in range(-half + 1, half + 1):
            for dq in range(-half + 1, half + 1):
                ok = (r + dr >= 0) & (r + dr < canvas.h) & (q + dq >= 0) & (q + dq < canvas.w)
                canvas.rgb[r[ok] + dr, q[ok] + dq] = color

    paint(grid.known_free_mask(), (215, 225, 240))
    paint(grid.occupied_mask(), (0, 0, 0))
    write_png(path, canvas.rgb)
    return True


def fault_table(rows: list[dict[str, Any]]) -> list[str]:
    """The markdown table of injected faults (see :mod:`mazebot.bench.fault_metrics`)."""

    def num(v: Any, unit: str = "") -> str:
        return "—" if v is None else f"{v:g}{unit}"

    def yes(v: Any) -> str:
        return "—" if v is None else ("yes" if v else "**no**")

    out = [
        "| fault | detected ms | motors zero ms | recovered | map intact | alive | re-localized s | "
        "scanning again s | passed | detected by |",
        "|---|---:|---:|---|---|---|---:|---:|---|---|",
    ]
    for r in rows:
        if not r.get("injected_s") and r.get("injected") is False:
            out.append(f"| {r['fault']} | not injected | | | | | | | **no** | |")
            continue
        zero = num(r.get("motors_zero_ms")) if r.get("must_stop") else "— (drives on)"
        by = (r.get("detected_by") or "").replace("|", "/")
        out.append(
            f"| {r['fault']} | {num(r.get('detected_ms'))} | {zero} | {yes(r.get('recovered'))} | "
            f"{yes(r.get('map_intact'))} | {yes(r.get('alive'))} | {num(r.get('relocalized_s'))} | "
            f"{num(r.get('scanning_again_s'))} | {yes(r.get('passed'))} | {by[:110]} |"
        )
    return out


def budget_table(metrics: list[dict[str, Any]]) -> list[str]:
    """Each part's thread CPU, medians over the runs: ms per robot-second, p99 ms per call."""
    rows = ["| part | CPU ms per robot-second | p50 ms per call | p99 ms per call | calls per robot-second |",
            "|---|---|---|---|---|"]
    budgets = [m["cpu_budget"] for m in metrics if m.get("cpu_budget")]
    if not budgets:
        return []
    for part in budgets[0]:
        def med(key: str, part: str = part) -> str:
            values = [b[part][key] for b in budgets if b[part][key] is not None]
            return f"{statistics.median(values):.3g}" if values else "null"
        rates = [b[part]["calls"] / m["time_s"] for b, m in zip(budgets, metrics, strict=False) if m["time_s"]]
        rate = f"{statistics.median(rates):.3g}" if rates else "null"
        rows.append(f"| {part} | {med('cpu_ms_per_s')} | {med('p50_ms')} | {med('p99_ms')} | {rate} |")
    return rows


def write_report(out_dir: Path, runs: list[tuple[dict[str, Any], RunRecord]], command: str) -> dict[str, Any]:
    out_dir.mkdir(parents=True, exist_ok=True)
    metrics = [m for m, _ in runs]
    lines = [
        "# mazebot benchmark", "", f"Command: `{command}`", "",
        "| maze | seed | done | sim s | wall s | x real time | path m | collisions | revisits | "
        "ATE rms m | ATE max m | heading rms ° | coverage | map F1 | scan ms p50 | scan ms p99 | "
        "loop closures | false closures |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for i, (m, record) in enumerate(runs):
        fig = f"run{i:02d}-{m['maze']}-seed{m['seed']}-trajectory.png"
        trajectory_figure(record, out_dir / fig)
        map_fig = f"run{i:02d}-{m['maze']}-seed{m['seed']}-map.png"
        m["figures"] = {"trajectory": fig, "map": map_fig if map_figure(record, out_dir / map_fig) else None}
        events = list(record.state.planner_events) if record.state is not None else []
        if events:  # the planner's decisions, to read a run's detours against its trajectory figure
            log_name = f"run{i:02d}-{m['maze']}-seed{m['seed']}-planner.txt"
            write_atomic(out_dir / log_name, "".join(f"{t_s:8.2f}  {text}\n" for t_s, text in events))
            m["figures"]["planner_log"] = log_name

        def cell(v: Any) -> str:
            return "null" if v is None else str(v)

        lines.append("| " + " | ".join(cell(m[k]) for k in (
            "maze", "seed", "done", "time_s", "wall_s", "realtime_factor", "path_m", "collisions", "revisits",
            "ate_rms_m", "ate_max_m", "heading_rms_deg", "coverage", "map_f1", "scan_ms_p50", "scan_ms_p99",
            "loop_closures", "false_loop_closures")) + " |")
    summary = summarize(metrics)
    fault_rows = [row for m in metrics for row in (m.get("faults") or [])]
    if fault_rows:
        summary["faults"] = {"injected": len(fault_rows), "passed": sum(r["passed"] for r in fault_rows)}
        lines += ["", "## Faults", "", *fault_table(fault_rows)]
    results = {"command": command, "runs": metrics, "summary": summary}
    write_atomic(out_dir / "results.json", json.dumps(results, indent=2) + "\n")
    lines += ["", "## CPU per part of the daemon", "", *budget_table(metrics)]
    lines += ["", "## Summary (medians)", "", "```json", json.dumps(summary, indent=2), "```", "", "## Figures", ""]
    for m in metrics:
        lines.append(f"- {m['maze']} seed {m['seed']}: true trajectory (blue) and estimate (red) over the true "
                     f"walls: ![trajectory]({m['figures']['trajectory']})")
        if m["figures"]["map"]:
            lines.append(f"- {m['maze']} seed {m['seed']}: SLAM's map (black walls, grey-blue free) over the true "
                         f"walls (red): ![map]({m['figures']['map']})")
    lines += ["", "`null` marks a metric whose part mazebot does not have yet, never a guess. "
              "The estimate is " + (metrics[0]["estimate"] if metrics else "") + "; scan ms is SLAM's CPU time "
              "per scan (filter + ICP + grid), not virtual time."]
    write_atomic(out_dir / "report.md", "\n".join(lines) + "\n")
    return results


#: The columns of a CPU-quota run's table (``mazebot bench --cpu-quota``), in order.
QUOTA_COLUMNS = (
    ("maze", "maze"), ("seed", "seed"), ("cpu_quota_percent", "quota % of a core"), ("done", "done"),
    ("time_s", "time to done s"), ("coverage", "coverage"), ("collisions", "collisions"),
    ("control_jitter_ms_p99", "control p99 late ms"), ("control_ticks_late_over_50ms", "ticks over 50 ms late"),
    ("host_steal_s", "host steal s"), ("slam_scans_dropped", "revolutions dropped"),
    ("slam_queue_peak", "most revolutions waiting for SLAM"), ("slam_queue_behind", "revolutions queued 4+ behind"),
    ("slam_worker_pauses", "loop-closure worker paused (times)"),
    ("faults_raised", "faults raised"), ("daemon_cpu_percent", "daemon CPU % of a core (raw, cgroup)"),
    ("daemon_cpu_percent_sim_out", "daemon CPU % of a core, the simulator's GPIO share out"),
    ("gpio_thread_cpu_percent", "GPIO edge thread % of a core"), ("gpio_thread_us_per_edge", "its µs per edge"),
    ("gpio_sim_path_us_per_edge", "stand-in's loop µs per edge"), ("gpio_pi_path_us_per_edge", "Pi path µs per edge"),
    ("daemon_cpu_percent_of_quota", "% of quota"), ("cfs_throttled", "throttled periods"),
    ("cfs_periods", "periods"), ("daemon_rss_mb_peak", "daemon RSS MB peak"),
    ("daemon_pss_mb_peak", "daemon PSS MB peak"), ("world_cpu_percent", "world CPU % of a core"),
    ("world_rss_mb_peak", "world RSS MB peak"), ("loadavg_before", "load average before"),
)


#: The rows of a CPU-quota report's "where the daemon's CPU went" (:func:`mazebot.bench.quota_run.cpu_by_thread`).
WHERE_ROWS = (
    ("loop_thread_ms_per_s", "the event loop's thread"),
    ("loop_thread_outside_parts_ms_per_s", "of it outside the parts' meters"),
    ("process_other_threads_ms_per_s", "the daemon process's other threads, the GPIO edge thread's own aside"),
    ("other_processes_ms_per_s", "the other processes (control, loop-closure worker, fork server)"),
)


def write_quota_report(out_dir: Path, runs: list[dict[str, Any]], command: str) -> dict[str, Any]:
    """results.json and report.md of CPU-quota runs (no figures: the world lived in another process)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    for i, r in enumerate(runs):  # the planner's decisions, to read a run that ended early
        events = r.pop("planner_events", None) or []
        if events:
            name = f"run{i:02d}-{r['maze']}-seed{r['seed']}-planner.txt"
            write_atomic(out_dir / name, "".join(f"{t_s:8.2f}  {text}\n" for t_s, text in events))
            r["planner_log"] = name

    def cell(key: str, v: Any) -> str:
        if key == "cpu_quota_percent" and v is None:
            return "no limit"
        return "null" if v is None else str(v)

    summary: dict[str, Any] = {"runs": len(runs), "done": sum(1 for r in runs if r["done"])}
    for key in ("time_s", "coverage", "control_jitter_ms_p99", "daemon_cpu_percent", "daemon_cpu_percent_sim_out",
                "daemon_cpu_percent_of_quota", "daemon_rss_mb_peak"):
        values = [r[key] for r in runs if r.get(key) is not None]
        summary[f"{key}_median"] = round(statistics.median(values), 4) if values else None
    summary["collisions_total"] = sum(r["collisions"] or 0 for r in runs)
    steals = [r["host_steal_s"] for r in runs if r.get("host_steal_s") is not None]
    summary["host_steal_s_total"] = round(sum(steals), 2) if steals else None
    results = {"command": command, "runs": runs, "summary": summary}
    write_atomic(out_dir / "results.json", json.dumps(results, indent=2) + "\n")
    lines = [
        "# mazebot benchmark on a share of one core", "", f"Command: `{command}`", "",
        "The daemon in a cgroup with the CPU quota (10 ms period), the simulated world in a process of its "
        "own outside it, on the real clock. CPU from the cgroup's own accounting, from the daemon's start "
        "(devices open) to the end of the run. \"The simulator's GPIO share out\": the same less what the "
        "GPIO edge thread (gpiozero's mock pins driven from the world's pipe, the stand-in for lgpio's "
        "callback thread) does per edge beyond the Pi's path (our decoder behind gpiozero's dispatch, lgpio's "
        "notification loop), times its edges; both timed in a loop after the run (mazebot.sim.edge_cost). "
        "The rest of the thread's CPU stays: a Python callback thread costs as much on the Pi.", "",
        "| " + " | ".join(title for _, title in QUOTA_COLUMNS) + " |",
        "|" + "---|" * len(QUOTA_COLUMNS),
    ]
    for r in runs:
        lines.append("| " + " | ".join(cell(key, r.get(key)) for key, _ in QUOTA_COLUMNS) + " |")
    errors = [f"- {r['maze']} seed {r['seed']}: {e}" for r in runs for e in r.get("errors") or []]
    if errors:
        lines += ["", "## Errors", "", *errors]
    drops = [f"- {r['maze']} seed {r['seed']}: {note}" for r in runs for note in r.get("slam_drop_notes") or []]
    if drops:  # a dropped revolution must be explainable from the report alone
        lines += ["", "## Revolutions dropped, and what held SLAM up", "", *drops]
    budget = budget_table([r for r in runs if r.get("cpu_budget") and r.get("time_s")])
    if budget:
        lines += ["", "## CPU per part of the daemon", "", *budget, "",
                  "Thread CPU of each part's own calls (medians over the runs); the cgroup's total above also "
                  "holds the event loop, the serial and GPIO threads and the interpreter."]
    where = [r for r in runs if r.get("loop_thread_ms_per_s") is not None and r.get("time_s")]
    if where:
        lines += ["", "## Where the daemon's CPU went", "", "| where | CPU ms per robot-second (median) |", "|---|---|"]
        for key, title in WHERE_ROWS:
            values = [r[key] for r in where if r.get(key) is not None]
            lines.append(f"| {title} | {statistics.median(values):.3g} |" if values else f"| {title} | null |")
        lines += ["", "The event loop's thread and the daemon process by their own thread and process CPU clocks, "
                  "read when the run started and ended; \"outside the parts\" is the loop's thread less the parts "
                  "that run on it (lidar decoding, odometry, SLAM per revolution, planner tick, health check); the "
                  "other processes are the cgroup's total less the daemon's process."]
    lines += ["", "## Summary (medians)", "", "```json", json.dumps(summary, indent=2), "```", "",
              "`null` marks a metric whose part was missing (e.g. no cgroup accounting), never a guess."]
    write_atomic(out_dir / "report.md", "\n".join(lines) + "\n")
    return results
