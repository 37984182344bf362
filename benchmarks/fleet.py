"""Fleet throughput against the device count: sharded RMI end steps per second, logs per minute.

For each device count the script starts itself in a subprocess. On a CPU-only
machine that subprocess gets ``XLA_FLAGS=--xla_force_host_platform_device_count=d``
(d host devices sharing the same cores); where an accelerator is present the flag
is not set and the first d accelerators are used. Per count it times

- ``rmijax.fleet.rmi_batch`` over ``--runs`` runs of ``preset_arm(--links)``
  (``--duration`` s each, window 100): end steps per second, compile apart;
- ``rmijax.fleet.simulate_batch`` over the same runs: plant steps per second;
- ``rmijax check`` over a folder of ``--runs`` CSV logs of those runs (read,
  sharded bands, detection, report.md/json; ``--figures`` adds the PNGs):
  logs per minute, after a warm-up pass.

Efficiency = throughput(d) / (d x throughput(1)). The device kind is recorded.

Run: python benchmarks/fleet.py [--devices 1 2 4] [--runs 16] [--json fleet.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import markdown_table, run_meta, table, write_json  # noqa: E402

COLUMNS = [
    ("devices", "devices", "{:>7d}"),
    ("kind", "kind", "{:>10s}"),
    ("compile_s", "compile s", "{:>9.1f}"),
    ("rmi_steps_per_s", "RMI end steps/s", "{:>15.0f}"),
    ("rmi_efficiency", "RMI eff.", "{:>8.2f}"),
    ("sim_steps_per_s", "sim steps/s", "{:>11.0f}"),
    ("sim_efficiency", "sim eff.", "{:>8.2f}"),
    ("logs_per_min", "logs/min", "{:>8.0f}"),
    ("logs_efficiency", "logs eff.", "{:>9.2f}"),
]


def _median_time(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    times.sort()
    return times[len(times) // 2]


def worker(args):
    """Measure one device count (this process already has its devices)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    import rmijax
    from rmijax import fleet
    from rmijax.apps import check
    from rmijax.io import write_csv

    devices = jax.devices()[: args.worker]
    if len(devices) < args.worker:
        raise SystemExit(f"asked for {args.worker} devices, found {len(jax.devices())}")
    mesh = fleet.device_mesh(devices)
    n = args.links
    params = rmijax.preset_arm(n)
    shapes = ["sine", "slow_sine", "composite", "hold"]
    trajs = [
        rmijax.trajectory([shapes[(r + j) % len(shapes)] for j in range(n)], duration=args.duration)
        for r in range(args.runs)
    ]
    end_steps = sum(t.n_steps + 1 for t in trajs)

    t0 = time.perf_counter()
    jax.block_until_ready(fleet.rmi_batch(trajs, params, mesh=mesh))
    first = time.perf_counter() - t0
    rmi_s = _median_time(lambda: fleet.rmi_batch(trajs, params, mesh=mesh), args.repeats)

    th = rmijax.monte_carlo_parameters(params, args.runs, corners=False, seed=0)
    fault = [rmijax.Fault("stuck_sensors", n - 1, args.duration / 2)]
    fleet.simulate_batch(trajs, params, th, faults=fault, mesh=mesh)
    sim_s = _median_time(
        lambda: fleet.simulate_batch(trajs, params, th, faults=fault, mesh=mesh), args.repeats
    )
    _, readings = fleet.simulate_batch(trajs, params, th, faults=fault, mesh=mesh)

    with tempfile.TemporaryDirectory() as folder:
        names = [f"joint{j + 1}" for j in range(n)]
        for r, traj in enumerate(trajs):
            write_csv(
                f"{folder}/run{r:04d}.csv",
                time=np.asarray(traj.t),
                joint_names=names,
                q_d=traj.q_d,
                qd_d=traj.qd_d,
                qdd_d=traj.qdd_d,
                readings=readings[r],
            )
        command = [folder, "--robot", f"preset{n}", "--out", f"{folder}/out", "--no-progress"]
        command += ["--devices", str(args.worker), "--force", "--batch", str(args.runs)]
        if not args.figures:
            command += ["--no-figures"]
        check.main(command)  # warm-up: compiles
        logs_s = _median_time(lambda: check.main(command), max(1, args.repeats // 2))

    record = {
        "devices": len(devices),
        "kind": devices[0].device_kind,
        "platform": devices[0].platform,
        "links": n,
        "runs": args.runs,
        "duration_s": args.duration,
        "end_steps": end_steps,
        "compile_s": first - rmi_s,
        "rmi_s": rmi_s,
        "rmi_steps_per_s": end_steps / rmi_s,
        "sim_s": sim_s,
        "sim_steps_per_s": end_steps / sim_s,
        "logs_s": logs_s,
        "logs_per_min": 60 * args.runs / logs_s,
        "figures": args.figures,
    }
    print("RECORD " + json.dumps(record), flush=True)


def _accelerator_count():
    import jax

    return sum(d.platform != "cpu" for d in jax.devices())


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--devices", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--links", type=int, default=2, help="preset_arm(n)")
    parser.add_argument("--runs", type=int, default=16, help="runs (and logs) per batch")
    parser.add_argument("--duration", type=float, default=3.0, help="s per run")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats (median)")
    parser.add_argument("--figures", action="store_true", help="check writes PNGs too")
    parser.add_argument("--json", default=None, help="write results here")
    parser.add_argument("--markdown", action="store_true", help="print a Markdown table")
    parser.add_argument("--worker", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker is not None:
        return worker(args)

    accelerators = _accelerator_count()
    records = []
    for count in args.devices:
        env = dict(os.environ)
        if not accelerators:
            flags = env.get("XLA_FLAGS", "")
            env["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={count}".strip()
        elif count > accelerators:
            print(f"skip {count} devices: {accelerators} accelerator(s)", flush=True)
            continue
        argv_worker = [sys.executable, __file__, "--worker", str(count)]
        for key in ("links", "runs", "duration", "repeats"):
            argv_worker += [f"--{key}", str(getattr(args, key))]
        if args.figures:
            argv_worker.append("--figures")
        done = subprocess.run(argv_worker, env=env, capture_output=True, text=True)
        if done.returncode != 0:
            print(done.stderr[-3000:], file=sys.stderr)
            raise SystemExit(f"the {count}-device run failed")
        line = next(v for v in done.stdout.splitlines() if v.startswith("RECORD "))
        records.append(json.loads(line[len("RECORD ") :]))
        base = records[0]
        for key in ("rmi", "sim", "logs"):
            rate = "logs_per_min" if key == "logs" else f"{key}_steps_per_s"
            scale = records[-1]["devices"] / base["devices"]
            records[-1][f"{key}_efficiency"] = records[-1][rate] / (scale * base[rate])
        print(
            table(records[-1:], COLUMNS).splitlines()[-1]
            if len(records) > 1
            else table(records, COLUMNS),
            flush=True,
        )
    meta = {
        **run_meta("benchmarks/fleet.py", argv, dtype="float64"),
        "cores": os.cpu_count(),
        "args": vars(args),
        "forced_host_devices": not accelerators,
        "load_average_after": os.getloadavg(),
    }
    write_json(args.json, records, meta)
    if args.markdown:
        print(markdown_table(records, COLUMNS))
    print(
        f"device: {meta['device']}; load average {meta['load_average_after'][0]:.1f}; "
        "efficiency = rate(d) / (d x rate(1))"
    )


if __name__ == "__main__":
    main()
