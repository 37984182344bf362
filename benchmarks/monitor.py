"""Per-tick latency of the online monitor's jitted ``update`` (SPEC section 8).

One tick = the bounds of one end step (all 4n tracks, max and min, full window) plus
the detector, after warm-up, block_until_ready. The 1 ms column is the budget of a
1 kHz torque loop.

With ``--robot panda`` (or ``iiwa14``, ``ur5e``) the arm is a shipped real arm with its
default box (``rmijax.default_box``: p = 3n + 1 parameters, 22 on the Panda), on the
real-arm job's pick-and-place move, and every monitor method (``--methods``) is timed;
each row also says whether the method's fault-free run raises an alarm: the job's true
robot (every parameter at nominal + 0.6 (hi - nominal)) simulated on the move, its
readings checked against the method's bands, so that the fastest alarm-free method can
be read off.

``--latency`` times the ticks as a control process would run them: JAX's synchronous
CPU dispatch (``jax.config.update("jax_cpu_enable_async_dispatch", False)``: the tick
runs on the calling thread, no hand-off to a dispatch thread) and the process pinned to
one core (``os.sched_setaffinity``, so XLA's thread pool has one thread and its small
kernels are not handed between cores). On a 2-core VM those hand-offs, not the
arithmetic, are most of a single-step tick. Both settings are the user's (process-wide);
the library sets neither.

Run: python benchmarks/monitor.py [--links 1 2 3 4 5 6] [--json monitor.json]
     python benchmarks/monitor.py --robot panda --json monitor_panda.json
     python benchmarks/monitor.py --robot panda --latency --json monitor_panda_latency.json
"""

from __future__ import annotations

import argparse
import sys
import time

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import (  # noqa: E402
    REAL_TIME_BUDGET_S,
    peak_rss_mb,
    run_meta,
    table,
    time_calls,
    write_json,
)


def _time_ticks(update, prepared, args):
    """First-call (compile) seconds and the timing of ``update`` over prepared tick inputs."""
    import jax

    def tick_args(i):
        return prepared[i % len(prepared)]

    t0 = time.perf_counter()
    jax.block_until_ready(update(*tick_args(0)))
    compile_s = time.perf_counter() - t0
    return compile_s, time_calls(update, tick_args, calls=args.calls, max_seconds=args.max_seconds)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--links",
        type=int,
        nargs="+",
        default=[1, 2, 3, 4, 5, 6],
        help="arm sizes (preset_arm(n)); 8 works but takes minutes per tick",
    )
    parser.add_argument("--mode", choices=["coupled", "per_joint"], default="coupled")
    parser.add_argument("--dtype", choices=["float32", "float64"], default="float64")
    parser.add_argument(
        "--window",
        type=int,
        default=None,
        help="window N in ticks (default 100; with --robot each method's default: "
        "100 for rmi, 2 for short_window)",
    )
    parser.add_argument("--calls", type=int, default=200, help="timed ticks per size (max)")
    parser.add_argument(
        "--max-seconds",
        type=float,
        default=20.0,
        help="stop timing a size after this long (at least 2 ticks)",
    )
    parser.add_argument(
        "--robot",
        default=None,
        help="a shipped real arm (panda, iiwa14, ur5e) instead of the planar sizes",
    )
    parser.add_argument(
        "--methods",
        nargs="+",
        default=["rmi", "short_window"],
        help="monitor methods timed with --robot (default: all the monitor runs)",
    )
    parser.add_argument(
        "--segment-time", type=float, default=0.5, help="s per segment of the --robot move"
    )
    parser.add_argument(
        "--latency",
        action="store_true",
        help="synchronous dispatch and the process pinned to one core (see the docstring)",
    )
    parser.add_argument("--json", default=None, help="write results here")
    args = parser.parse_args(argv)
    _setup_latency(args)
    if args.robot is not None:
        return robot_main(args, argv)
    args.window = 100 if args.window is None else args.window

    import jax

    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import rmijax

    dtype = jnp.float64 if args.dtype == "float64" else jnp.float32
    records = []
    for n in args.links:
        params = rmijax.preset_arm(n, dtype=dtype)
        traj = rmijax.trajectory(["slow_sine"] + ["sine"] * (n - 1), duration=4.0, dtype=dtype)
        mon = rmijax.monitor(params, dt=traj.dt, mode=args.mode, window=args.window)
        update = jax.jit(mon.update)
        state = mon.init(traj.q_d[0], traj.qd_d[0])

        # Inputs prepared before timing (ticks 150..349: full windows), so that only
        # the update itself is timed, as in a control loop that already holds them.
        prepared = [
            (state, (traj.q_d[k], traj.qd_d[k], traj.qdd_d[k]), traj.x_n[k])
            for k in range(150, 350)
        ]
        jax.block_until_ready(prepared)

        compile_s, timing = _time_ticks(update, prepared, args)
        records.append(
            {
                "n": n,
                "K": 4**n,
                "mode": args.mode,
                "dtype": args.dtype,
                "window": args.window,
                "compile_s": compile_s,
                "p50_ms": timing["p50_s"] * 1e3,
                "p99_ms": timing["p99_s"] * 1e3,
                "calls": timing["calls"],
                "budget_ratio": timing["p50_s"] / REAL_TIME_BUDGET_S,
                "peak_rss_mb": peak_rss_mb(),
            }
        )
        print(
            table(records[-1:], COLUMNS).splitlines()[-1]
            if len(records) > 1
            else table(records, COLUMNS),
            flush=True,
        )
    meta = {**run_meta("benchmarks/monitor.py", argv, dtype=args.dtype), "args": vars(args)}
    write_json(args.json, records, meta)
    print(f"device: {meta['device']}; budget_ratio = p50 / 1 ms (below 1: real time at 1 kHz)")


def robot_main(args, argv):
    """Per-tick latency of each monitor method on a real arm, and its fault-free alarms."""
    import jax

    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    import numpy as np

    import rmijax
    from rmijax.apps.real_arm import TRUE_FRACTION, home_pose, pick_and_place

    params = rmijax.load_robot(args.robot, **rmijax.default_box(args.robot), dtype=args.dtype)
    traj = pick_and_place(home_pose(args.robot), segment_time=args.segment_time)
    nominal, hi = np.asarray(params.nominal), np.asarray(params.hi)
    th_true = nominal + TRUE_FRACTION * (hi - nominal)
    _, readings = rmijax.simulate(traj, params, th_true)
    records = []
    for method in args.methods:
        mon = rmijax.monitor(
            params,
            kp=traj.kp,
            kd=traj.kd,
            dt=traj.dt,
            method=method,
            window=mon_window(method, args.window),
        )
        update = jax.jit(mon.update)
        step = jax.jit(
            lambda state, k, update=update: update(state, _desired(traj, k), readings[k])
        )
        # The fault-free run, tick by tick through the monitor itself (first alarm, count).
        state = mon.init(traj.q_d[0], traj.qd_d[0])
        alarms, first = 0, None
        for k in range(traj.n_steps + 1):
            state, out = step(state, k)
            if bool(np.any(np.asarray(out.alarm))):
                alarms += 1
                first = k if first is None else first
        # Timed ticks: inputs prepared beforehand (full windows where the run allows).
        start = min(mon_window(method, args.window) + 10, traj.n_steps // 2)
        state = mon.init(traj.q_d[0], traj.qd_d[0])
        for k in range(start):
            state, _ = step(state, k)
        prepared = [(state, _desired(traj, k), readings[k]) for k in range(start, traj.n_steps + 1)]
        jax.block_until_ready(prepared)

        compile_s, timing = _time_ticks(update, prepared, args)
        records.append(
            {
                "robot": args.robot,
                "method": method,
                "n": params.n_joints,
                "p": params.n_params,
                "mode": args.mode,
                "dtype": args.dtype,
                "window": mon_window(method, args.window),
                "compile_s": compile_s,
                "p50_ms": timing["p50_s"] * 1e3,
                "p99_ms": timing["p99_s"] * 1e3,
                "calls": timing["calls"],
                "budget_ratio": timing["p50_s"] / REAL_TIME_BUDGET_S,
                "fault_free_alarm_ticks": alarms,
                "latency_setup": args.latency,
                "first_false_alarm_s": None if first is None else first * float(traj.dt),
                "peak_rss_mb": peak_rss_mb(),
            }
        )
        print(table(records[-1:], ROBOT_COLUMNS), flush=True)
    clean = [r for r in records if r["fault_free_alarm_ticks"] == 0]
    if clean:
        best = min(clean, key=lambda r: r["p50_ms"])
        print(f"fastest alarm-free method: {best['method']} ({best['p50_ms']:.3f} ms p50)")
    meta = {**run_meta("benchmarks/monitor.py", argv, dtype=args.dtype), "args": vars(args)}
    meta["steps"] = int(traj.n_steps)
    write_json(args.json, records, meta)
    print(f"device: {meta['device']}; load average {meta['load_avg']}")
    return records


def _setup_latency(args):
    """Apply ``--latency`` before JAX creates its CPU client (the pool is sized then)."""
    import os

    import jax

    if args.latency:
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
        jax.config.update("jax_cpu_enable_async_dispatch", False)
    args.cpus = sorted(os.sched_getaffinity(0))
    args.async_dispatch = bool(jax.config.values["jax_cpu_enable_async_dispatch"])


def mon_window(method, window):
    from rmijax.detection.monitor import DEFAULT_WINDOWS

    return DEFAULT_WINDOWS[method] if window is None else window


def _desired(traj, k):
    return (traj.q_d[k], traj.qd_d[k], traj.qdd_d[k])


ROBOT_COLUMNS = [
    ("robot", "robot", "{:>6s}"),
    ("method", "method", "{:>12s}"),
    ("p", "p", "{:>3d}"),
    ("window", "N", "{:>4d}"),
    ("compile_s", "compile s", "{:>9.2f}"),
    ("p50_ms", "p50 ms", "{:>9.3f}"),
    ("p99_ms", "p99 ms", "{:>9.3f}"),
    ("calls", "calls", "{:>5d}"),
    ("budget_ratio", "x 1 ms", "{:>8.2f}"),
    ("fault_free_alarm_ticks", "false-alarm ticks", "{:>17d}"),
]

COLUMNS = [
    ("n", "n", "{:>2d}"),
    ("K", "K", "{:>6d}"),
    ("mode", "mode", "{:>9s}"),
    ("dtype", "dtype", "{:>7s}"),
    ("compile_s", "compile s", "{:>9.2f}"),
    ("p50_ms", "p50 ms", "{:>9.3f}"),
    ("p99_ms", "p99 ms", "{:>9.3f}"),
    ("calls", "calls", "{:>5d}"),
    ("budget_ratio", "x 1 ms", "{:>8.2f}"),
    ("peak_rss_mb", "RSS MB", "{:>7.0f}"),
]

if __name__ == "__main__":
    main()
