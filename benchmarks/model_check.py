"""Cost of the user-model check (rmijax.check_model) against a 15 s two-joint rmi run.

The check runs once per (model, box, states) before any band; its cost is one
small XLA compilation. This script measures, in one fresh process:

- ``rmi`` on the paper's two-joint arm (``hold``/``sine``, 15 s, 1501 end steps),
  the first call (compile + run) and a warm call;
- ``check_model`` on the same arm as a user would bring it (an untrusted copy of
  the model, with and without its closed-form ``forward_dynamics``): the first
  call (compile + evaluation) and a repeated call (cached).

    PYTHONPATH=src python3 benchmarks/model_check.py [--json out.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import jax

jax.config.update("jax_enable_x64", True)

from _common import run_meta  # noqa: E402

import rmijax  # noqa: E402
from rmijax.robots import check  # noqa: E402


def _timed(fn):
    started = time.perf_counter()
    out = fn()
    jax.block_until_ready(getattr(out, "upper", out))
    return time.perf_counter() - started


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", help="also write the numbers to this JSON file")
    args = parser.parse_args(argv)
    traj = rmijax.trajectory(["hold", "sine"], duration=15.0)
    params = rmijax.paper_arm2()
    rows = {}
    user = dataclasses.replace(params, model=dataclasses.replace(params.model, trusted=False))
    bare = dataclasses.replace(
        params,
        model=dataclasses.replace(params.model, trusted=False, forward_dynamics=None),
    )
    rows["check_model first call (user copy, with forward_dynamics)"] = _timed(
        lambda: check.check_model(user, traj)
    )
    rows["check_model repeated call (cached)"] = _timed(lambda: check.check_model(user, traj))
    rows["check_model first call (user copy, no forward_dynamics)"] = _timed(
        lambda: check.check_model(bare, traj)
    )
    rows["rmi 15 s two-joint, first call (compile + run)"] = _timed(
        lambda: rmijax.rmi(traj, params)
    )
    rows["rmi 15 s two-joint, warm call"] = _timed(lambda: rmijax.rmi(traj, params))
    # A user's own two-joint model: the arm's M and h as plain functions, nothing declared.
    model = rmijax.RobotModel(2, 4, params.model.mass_matrix, params.model.bias, name="user")
    mine = rmijax.uncertain_robot(model, params.nominal, params.lo, params.hi)
    rows["check_model first call (user model: M and h only)"] = _timed(
        lambda: check.check_model(mine, traj)
    )
    rows["rmi 15 s two-joint user model, first call (enumeration)"] = _timed(
        lambda: rmijax.rmi(traj, mine)
    )
    first = rows["check_model first call (user copy, with forward_dynamics)"]
    run = rows["rmi 15 s two-joint, first call (compile + run)"]
    print("| what | seconds |")
    print("|---|---|")
    for label, seconds in rows.items():
        print(f"| {label} | {seconds:.4f} |")
    cached = rows["check_model repeated call (cached)"]
    warm = rows["rmi 15 s two-joint, warm call"]
    user_first = rows["check_model first call (user model: M and h only)"]
    user_run = rows["rmi 15 s two-joint user model, first call (enumeration)"]
    print(
        f"\nuser model: check (first call) / its rmi (first call) = "
        f"{100 * user_first / user_run:.1f}%"
    )
    print(
        f"arm copy: check (first call) / rmi (first call) = {100 * first / run:.1f}%; "
        f"cached check / warm rmi = {100 * cached / warm:.3f}%"
    )
    if args.json:
        with open(args.json, "w") as handle:
            meta = run_meta("benchmarks/model_check.py", dtype="float64")
            json.dump({"meta": meta, "seconds": rows}, handle, indent=1)


if __name__ == "__main__":
    main()
