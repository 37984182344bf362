"""Cost of the user-model check (rmijax.check_model) on a 15 s two-joint rmi run.

The check runs once per (model, box, states) before any band: it traces the
model's functions and compiles one small XLA program. Much of a first call's
time in a fresh process is JAX's and XLA's own start-up (the first trace, the
first compilation), which the ``rmi`` call right after would otherwise pay. So
the cost that matters is the *marginal* one: how much longer a user's first
``rmi`` call takes with the check than without it.

Measured over ``--repeats`` pairs of fresh processes (alternating, so a change
of machine load hits both sides), each running the paper's two-joint arm
(``hold``/``sine``, 15 s, 1501 end steps) as a user would bring it (an
untrusted copy of the model with its closed-form ``forward_dynamics``):

- *with*: ``check_model`` (first call), then ``rmi`` (its own check is then a
  cache hit): the time of both;
- *without*: the same ``rmi`` call with the check switched off.

The marginal cost is the median of *with* minus the median of *without*, and
its share of *without*, in CPU seconds of the process (all its threads:
``time.process_time``, which a busy machine disturbs far less than the wall
clock) and in wall seconds (on a shared machine the wall-clock difference is
mostly noise: compare the spread of the runs). The check's own first-call time
against the first ``rmi`` call is reported too (an upper bound on its share,
since part of it is start-up the ``rmi`` call would otherwise pay). Each child
also reports a warm ``rmi`` call and a cached check.

    PYTHONPATH=src python3 benchmarks/model_check.py [--repeats 5] [--json out.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import time

import numpy as np


def _child(mode):
    import jax

    jax.config.update("jax_enable_x64", True)
    import rmijax
    from rmijax.robots import check

    traj = rmijax.trajectory(["hold", "sine"], duration=15.0)
    params = rmijax.paper_arm2()
    user = dataclasses.replace(params, model=dataclasses.replace(params.model, trusted=False))
    if mode == "without":
        for module in list(sys.modules.values()):
            if getattr(module, "__name__", "").startswith("rmijax") and hasattr(
                module, "check_model"
            ):
                module.check_model = lambda *args, **kwargs: None
    out = {}
    started, cpu = time.perf_counter(), time.process_time()
    if mode == "with":
        check.check_model(user, traj)
        out["check_first_s"] = time.perf_counter() - started
        out["check_first_cpu_s"] = time.process_time() - cpu
    jax.block_until_ready(rmijax.rmi(traj, user).upper)
    out["first_s"] = time.perf_counter() - started
    out["first_cpu_s"] = time.process_time() - cpu
    t0 = time.perf_counter()
    jax.block_until_ready(rmijax.rmi(traj, user).upper)
    out["warm_rmi_s"] = time.perf_counter() - t0
    if mode == "with":
        t0 = time.perf_counter()
        check.check_model(user, traj)
        out["check_cached_s"] = time.perf_counter() - t0
    print(json.dumps(out))


def _spawn(mode):
    env = dict(os.environ)
    src = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "src")
    env["PYTHONPATH"] = src + os.pathsep + env.get("PYTHONPATH", "")
    done = subprocess.run(
        [sys.executable, os.path.abspath(__file__), "--child", mode],
        capture_output=True,
        text=True,
        env=env,
        check=True,
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="fresh-process pairs")
    parser.add_argument("--json", help="also write the numbers to this JSON file")
    parser.add_argument("--child", choices=["with", "without"], help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        _child(args.child)
        return
    runs = {"with": [], "without": []}
    for i in range(args.repeats):
        for mode in ("with", "without") if i % 2 == 0 else ("without", "with"):
            runs[mode].append(_spawn(mode))
            print(mode, runs[mode][-1], flush=True)
    med = {
        key: float(np.median([r[key] for r in runs[mode]]))
        for mode in runs
        for key in runs[mode][0]
        if mode == "with"
    }
    summary = {}
    for unit, key in (("CPU s", "first_cpu_s"), ("wall s", "first_s")):
        with_s = float(np.median([r[key] for r in runs["with"]]))
        without_s = float(np.median([r[key] for r in runs["without"]]))
        marginal = with_s - without_s
        summary |= {
            f"first rmi call with the check (check + rmi), median {unit}": with_s,
            f"first rmi call without the check, median {unit}": without_s,
            f"marginal cost of the check, {unit}": marginal,
            f"marginal cost, % of the first rmi call ({unit})": 100 * marginal / without_s,
        }
    summary |= {
        "check_model first call in a fresh process (incl. JAX/XLA start-up), median wall s": med[
            "check_first_s"
        ],
        "check_model first call in a fresh process, median CPU s": med["check_first_cpu_s"],
        "check_model first call, % of the first rmi call without it (CPU s)": 100
        * med["check_first_cpu_s"]
        / float(np.median([r["first_cpu_s"] for r in runs["without"]])),
        "check_model first call, % of the first rmi call without it (wall s)": 100
        * med["check_first_s"]
        / float(np.median([r["first_s"] for r in runs["without"]])),
        "check_model cached call, median s": med["check_cached_s"],
        "rmi warm call, median s": med["warm_rmi_s"],
    }
    print("| what | value |")
    print("|---|---|")
    for label, value in summary.items():
        print(f"| {label} | {value:.4f} |")
    if args.json:
        sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
        from _common import run_meta

        with open(args.json, "w") as handle:
            meta = run_meta("benchmarks/model_check.py", dtype="float64")
            json.dump({"meta": meta, "summary": summary, "runs": runs}, handle, indent=1)


if __name__ == "__main__":
    main()
