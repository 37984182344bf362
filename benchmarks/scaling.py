"""How exact RMI scales with the number of links: online latency, offline throughput, memory.

The engine under test is ``rmijax.rmi`` with its default ``search="auto"`` (for the
planar arm an exact search over the 2^n mass corners, for real arms the
``LinearDynamics`` search of ``rmijax.methods.linear_search``; SPEC sections 4-5
unchanged). For each arm size n (``preset_arm(n)``, K = 4^n corners) or shipped real
arm (``--robot``: ``load_robot(name, **default_box(name))``: masses +-10 %, payload
0-1 kg, viscous and Coulomb friction scaled to each joint's inertia), K = 2^p corners,
p = 3n + 1, on a pick-and-place move
home -> home + 0.3 rad -> home, 1.5 s per segment), mode and dtype:
- compile time of the online step (first call minus a timed call);
- online per-step latency p50/p99: one jitted call returning all bounds of one end
  step (all 4n tracks, max and min, full window), after warm-up, block_until_ready
  (SPEC section 8); at most ``--calls`` calls or ``--max-seconds`` per size;
- offline throughput: end steps per second of ``rmi`` over a run, compile apart; a
  whole 15 s run (1501 end steps) where that takes under ``--offline-seconds``, else as
  many end steps as fit in it (at least 2; stated in the table);
- peak RSS of the process and the ratio of the p50 latency to the 1 ms budget;
- the speed-up over the plain NumPy reference (tests/reference_numpy.py) on the same
  end steps, for ``--numpy-links``, and over plain enumeration of all corners
  (``search="enumerate"``) for ``--enumerate-links``;
- XLA's flop count of one end step, the achieved GFLOP/s and its share of the
  machine's peak (``--peak-gflops``), and XLA's working set of one end step.

Run: python benchmarks/scaling.py --links 6     (see --help)
     python benchmarks/scaling.py --robot panda iiwa14 ur5e --mode coupled
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _common import (  # noqa: E402
    REAL_TIME_BUDGET_S,
    markdown_table,
    peak_rss_mb,
    read_json,
    run_meta,
    table,
    time_calls,
    write_json,
)

COLUMNS = [
    ("arm", "arm", "{:>7s}"),
    ("n", "n", "{:>2d}"),
    ("K", "K", "{:>7d}"),
    ("mode", "mode", "{:>9s}"),
    ("dtype", "dtype", "{:>7s}"),
    ("compile_s", "compile s", "{:>9.2f}"),
    ("p50_ms", "p50 ms", "{:>10.3f}"),
    ("p99_ms", "p99 ms", "{:>10.3f}"),
    ("calls", "calls", "{:>5d}"),
    ("offline_steps", "offl. steps", "{:>11d}"),
    ("offline_steps_per_s", "steps/s", "{:>9.1f}"),
    ("budget_ratio", "x 1 ms", "{:>9.2f}"),
    ("temp_mb", "XLA MB", "{:>7.2g}"),
    ("peak_rss_mb", "RSS MB", "{:>7.0f}"),
    ("flops", "flop/step", "{:>9.2e}"),
    ("gflops", "GFLOP/s", "{:>7.1f}"),
    ("peak_pct", "% peak", "{:>6.1f}"),
    ("enumerate_speedup", "vs enum.", "{:>8s}"),
    ("numpy_speedup", "vs NumPy", "{:>8s}"),
]


def _paths(n):
    return ["slow_sine"] + ["sine"] * (n - 1)


ROBOT_HOMES = {
    "panda": [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785],
    "iiwa14": [0.0, 0.5, 0.0, -1.2, 0.0, 0.8, 0.0],
    "ur5e": [0.0, -1.571, 1.571, -1.571, -1.571, 0.0],
}
"""Joint-space home poses of the shipped arms (rad) for the ``--robot`` move."""


class Problem:
    """One row's arm: ``params``, the timed trajectory and ``offline(count)``, a
    trajectory of ``count`` end steps."""

    def __init__(self, arm, n, corners, params, traj, offline):
        self.arm, self.n, self.corners = arm, n, corners
        self.params, self.traj, self.offline = params, traj, offline


def planar_problem(n, dtype):
    import rmijax

    params = rmijax.preset_arm(n, dtype=dtype)
    traj = rmijax.trajectory(_paths(n), duration=4.0, dtype=dtype)

    def offline(count):
        return rmijax.trajectory(_paths(n), duration=(count - 1) * 0.01, dtype=dtype)

    return Problem("planar", n, 4**n, params, traj, offline)


def robot_problem(name, dtype):
    import numpy as np

    import rmijax
    from rmijax.robots.loaders import default_box, load_robot

    params = load_robot(name, **default_box(name), dtype=dtype)
    home = np.asarray(ROBOT_HOMES[name])

    def move(segment_time):
        return rmijax.waypoint_trajectory(
            [home, home + 0.3, home], segment_time=segment_time, dt=0.01, dtype=dtype
        )

    def offline(count):
        return move(max(0.01, round((count - 1) / 2) * 0.01))

    return Problem(name, params.n_joints, 2**params.n_params, params, move(1.5), offline)


def step_flops(params, traj, mode, window, search="auto"):
    """XLA's flop count of one end step: one window step (all tracks, all corners) x N.

    XLA's cost analysis counts a loop body once, so a one-step window is analysed
    and scaled by the window length. It counts the HLO before fusion: work that
    XLA's fusion recomputes in several kernels is counted once.
    """
    import jax

    import rmijax

    one = jax.jit(lambda t: rmijax.rmi_step(traj, params, t, mode=mode, window=1, search=search))
    analysis = one.lower(5).compile().cost_analysis()
    if isinstance(analysis, list):
        analysis = analysis[0]
    return float(analysis.get("flops", float("nan"))) * window


def working_set_mb(step, t):
    """XLA's temporary buffers of one compiled end step, in MiB."""
    return step.lower(t).compile().memory_analysis().temp_size_in_bytes / 2**20


def measure(problem, mode, dtype_name, args):
    import jax
    import jax.numpy as jnp

    import rmijax

    n, params, traj = problem.n, problem.params, problem.traj
    step = jax.jit(lambda t: rmijax.rmi_step(traj, params, t, mode=mode, window=args.window))
    last = traj.n_steps - args.window - 1
    end_steps = [jnp.asarray(args.window + 1 + i % min(200, last)) for i in range(args.calls)]
    label = f"{problem.arm} n={n}"
    print(f"{label} {mode} {dtype_name}: timing the online step ...", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    jax.block_until_ready(step(end_steps[0]))
    first = time.perf_counter() - t0
    timing = time_calls(
        step, lambda i: (end_steps[i],), calls=args.calls, max_seconds=args.max_seconds
    )
    compile_s = max(first - timing["p50_s"], 0.0)

    # Offline: a whole 15 s run if it fits the time allowance, else a stated subset.
    # Every end step runs a full-length (masked) window, so any subset is representative.
    count = int(min(1501, max(2, args.offline_seconds / max(timing["p50_s"], 1e-9))))
    offline_traj = problem.offline(count)
    count = offline_traj.n_steps + 1
    diverged = False

    def offline_run():
        nonlocal diverged
        try:
            return rmijax.rmi(offline_traj, params, mode=mode, window=args.window).upper
        except rmijax.DivergedError:  # a box too wide for the loop: timed all the same
            diverged = True
            return None

    jax.block_until_ready(offline_run())  # compile and a first run
    t0 = time.perf_counter()
    jax.block_until_ready(offline_run())
    offline_rate = count / (time.perf_counter() - t0)
    if diverged:
        print(f"{label}: the bounds diverge (DivergedError); timings stand", file=sys.stderr)
    flops = step_flops(params, traj, mode, args.window)
    gflops = flops / timing["p50_s"] / 1e9
    record = {
        "arm": problem.arm,
        "n": n,
        "K": problem.corners,
        "mode": mode,
        "dtype": dtype_name,
        "window": args.window,
        "compile_s": compile_s,
        "p50_ms": timing["p50_s"] * 1e3,
        "p99_ms": timing["p99_s"] * 1e3,
        "calls": timing["calls"],
        "offline_steps": count,
        "offline_steps_per_s": offline_rate,
        "budget_ratio": timing["p50_s"] / REAL_TIME_BUDGET_S,
        "temp_mb": working_set_mb(step, end_steps[0]),
        "peak_rss_mb": peak_rss_mb(),
        "flops": flops,
        "gflops": gflops,
        "peak_pct": 100.0 * gflops / args.peak_gflops,
        "enumerate_speedup": "-",
        "numpy_speedup": "-",
        "diverged": diverged,
    }
    planar = problem.arm == "planar"
    if planar and n in args.enumerate_links:
        record.update(enumerate_comparison(params, traj, mode, args, timing["p50_s"]))
    if planar and n in args.numpy_links and dtype_name == "float64":
        record.update(numpy_comparison(n, mode, args))
    return record


def enumerate_comparison(params, traj, mode, args, p50_s):
    """p50 of the same end step with every corner enumerated (the definition of RMI)."""
    import jax
    import jax.numpy as jnp

    import rmijax

    def enumerated(t):
        return rmijax.rmi_step(traj, params, t, mode=mode, window=args.window, search="enumerate")

    step = jax.jit(enumerated)
    jax.block_until_ready(step(args.window + 1))
    ends = [jnp.asarray(args.window + 1 + i % 200) for i in range(args.calls)]
    timing = time_calls(step, lambda i: (ends[i],), calls=args.calls, max_seconds=args.max_seconds)
    return {
        "enumerate_p50_ms": timing["p50_s"] * 1e3,
        "enumerate_calls": timing["calls"],
        "enumerate_speedup": f"{timing['p50_s'] / p50_s:.1f}x",
    }


def numpy_comparison(n, mode, args):
    """Seconds per end step of the NumPy reference and of the JAX step, same end steps."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import rmijax

    sys.path.insert(0, str(HERE.parent / "tests"))
    from reference_numpy import PlanarArmNumpy, problem_args, rmi_reference

    params = rmijax.preset_arm(n, dtype=jnp.float64)
    traj = rmijax.trajectory(_paths(n), duration=4.0, dtype=jnp.float64)
    ends = list(range(args.window + 1, args.window + 1 + args.numpy_steps))
    t0 = time.perf_counter()
    rmi_reference(
        PlanarArmNumpy(n),
        *problem_args(traj, params),
        np.asarray(params.lo),
        np.asarray(params.hi),
        mode=mode,
        window=args.window,
        end_steps=ends,
    )
    numpy_per_step = (time.perf_counter() - t0) / len(ends)
    step = jax.jit(lambda t: rmijax.rmi_step(traj, params, t, mode=mode, window=args.window))
    jax.block_until_ready(step(ends[0]))
    t0 = time.perf_counter()
    for t in ends:
        jax.block_until_ready(step(t))
    jax_per_step = (time.perf_counter() - t0) / len(ends)
    return {
        "numpy_s_per_step": numpy_per_step,
        "jax_s_per_step": jax_per_step,
        "numpy_speedup": f"{numpy_per_step / jax_per_step:.0f}x",
    }


def plot(records, path, device_name):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    records = [r for r in records if r.get("arm", "planar") == "planar"]
    if not records:
        return
    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    groups = sorted({(r["mode"], r["dtype"]) for r in records})
    colors = {"coupled": "C0", "per_joint": "C1"}
    for mode, dtype in groups:
        rows = sorted(
            (r for r in records if (r["mode"], r["dtype"]) == (mode, dtype)), key=lambda r: r["n"]
        )
        ax.plot(
            [r["n"] for r in rows],
            [r["p50_ms"] for r in rows],
            marker="o" if dtype == "float64" else "s",
            ls="-" if dtype == "float64" else "--",
            color=colors[mode],
            label=f"{mode}, {dtype}",
        )
        enumerated = [r for r in rows if "enumerate_p50_ms" in r]
        if enumerated and dtype == "float64":
            ax.plot(
                [r["n"] for r in enumerated],
                [r["enumerate_p50_ms"] for r in enumerated],
                marker="x",
                ls=":",
                color=colors[mode],
                label=f"{mode}, {dtype}, all 4^n corners enumerated",
            )
    ax.axhline(1.0, color="k", lw=0.8, ls=":", label="1 ms (1 kHz loop)")
    ax.set_yscale("log")
    ax.set_xlabel("links n (K = 4^n corners)")
    ax.set_ylabel("online latency per end step, p50 [ms]")
    ax.set_title(
        f"exact RMI (p50 per end step), window {records[0]['window']}, {device_name}", fontsize=9
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--links",
        type=int,
        nargs="+",
        default=[1, 2, 3, 4, 5, 6],
        help="arm sizes, e.g. --links 6 or --links 1 2 3 8 (none with --robot only)",
    )
    parser.add_argument(
        "--robot",
        nargs="*",
        default=[],
        choices=sorted(ROBOT_HOMES),
        help="shipped real arms, e.g. --robot panda iiwa14 ur5e (mass scales, payload and "
        "friction uncertain; K = 2^(3n+1)); with --robot alone no planar sizes run",
    )
    parser.add_argument("--mode", choices=["coupled", "per_joint", "both"], default="both")
    parser.add_argument("--dtype", choices=["float32", "float64", "both"], default="float64")
    parser.add_argument("--window", type=int, default=100)
    parser.add_argument(
        "--calls",
        type=int,
        default=200,
        help="online calls per size (at least 100 where a call is < 1 s)",
    )
    parser.add_argument(
        "--max-seconds",
        type=float,
        default=30.0,
        help="stop timing one size after this long (at least 2 calls)",
    )
    parser.add_argument(
        "--offline-seconds",
        type=float,
        default=20.0,
        help="time allowance for the offline run of one size",
    )
    parser.add_argument(
        "--numpy-links",
        type=int,
        nargs="*",
        default=[1, 2, 3],
        help="sizes compared with the NumPy reference (float64)",
    )
    parser.add_argument(
        "--enumerate-links",
        type=int,
        nargs="*",
        default=[1, 2, 3, 4, 5],
        help="sizes also timed with every corner enumerated (search='enumerate')",
    )
    parser.add_argument(
        "--peak-gflops",
        type=float,
        default=147.0,
        help="the machine's peak GFLOP/s for the '%% peak' column (default: 2 AVX-512 "
        "cores at 2.3 GHz, float64, PERF_NOTES)",
    )
    parser.add_argument(
        "--numpy-steps",
        type=int,
        default=3,
        help="end steps (full windows) timed for the NumPy comparison",
    )
    parser.add_argument("--json", default=None, help="write results here")
    parser.add_argument("--plot", default=None, help="save the latency plot here (PNG)")
    parser.add_argument("--markdown", action="store_true", help="also print the table in Markdown")
    parser.add_argument(
        "--from-json",
        default=None,
        metavar="PATH",
        help="measure nothing: print (and --plot) the results of an earlier --json",
    )
    links_given = any(a == "--links" or a.startswith("--links=") for a in (argv or sys.argv[1:]))
    args = parser.parse_args(argv)
    if args.robot and not links_given:
        args.links = []
    if any(n < 1 for n in args.links):
        parser.error("--links must be >= 1")
    if args.from_json:
        records, meta = read_json(args.from_json)
        for rec in records:
            rec.setdefault("arm", "planar")
        print(table(records, COLUMNS))
        if args.markdown:
            print(markdown_table(records, COLUMNS))
        if args.plot:
            plot(records, args.plot, meta["device"])
        return

    import jax

    modes = ["coupled", "per_joint"] if args.mode == "both" else [args.mode]
    dtypes = ["float64", "float32"] if args.dtype == "both" else [args.dtype]
    if "float64" in dtypes:
        jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    makers = [lambda dt, n=n: planar_problem(n, dt) for n in args.links]
    makers += [lambda dt, name=name: robot_problem(name, dt) for name in args.robot]
    records = []
    for make in makers:
        for mode in modes:
            for dtype in dtypes:
                problem = make(jnp.float64 if dtype == "float64" else jnp.float32)
                records.append(measure(problem, mode, dtype, args))
                lines = table(records, COLUMNS).splitlines()
                print("\n".join(lines if len(records) == 1 else lines[-1:]), flush=True)
    dtype = "float64" if dtypes == ["float64"] else "float32" if dtypes == ["float32"] else "both"
    meta = {**run_meta("benchmarks/scaling.py", argv, dtype=dtype), "args": vars(args)}
    write_json(args.json, records, meta)
    if args.markdown:
        print(markdown_table(records, COLUMNS))
    if args.plot:
        plot(records, args.plot, meta["device"])
    print(
        f"device: {meta['device']}; x 1 ms = p50 / 1 ms; steps/s over 'offl. steps' end "
        "steps (1501 = a whole 15 s run); flop/step from XLA's cost analysis; vs enum. = "
        "speed-up over enumerating all corners"
    )


if __name__ == "__main__":
    main()
