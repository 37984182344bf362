"""Per-tick latency of the online monitor's jitted ``update`` (SPEC section 8).

One tick = the bounds of one end step (all 4n tracks, max and min, full window) plus
the detector, after warm-up, block_until_ready. The 1 ms column is the budget of a
1 kHz torque loop.

Run: python benchmarks/monitor.py [--links 1 2 3 4 5 6] [--json monitor.json]
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
    parser.add_argument("--window", type=int, default=100)
    parser.add_argument("--calls", type=int, default=200, help="timed ticks per size (max)")
    parser.add_argument(
        "--max-seconds",
        type=float,
        default=20.0,
        help="stop timing a size after this long (at least 2 ticks)",
    )
    parser.add_argument("--json", default=None, help="write results here")
    args = parser.parse_args(argv)

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

        def tick_args(i, prepared=prepared):
            return prepared[i % len(prepared)]

        t0 = time.perf_counter()
        jax.block_until_ready(update(*tick_args(0)))
        compile_s = time.perf_counter() - t0
        timing = time_calls(update, tick_args, calls=args.calls, max_seconds=args.max_seconds)
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
