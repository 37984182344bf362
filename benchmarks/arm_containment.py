"""Coupled containment on the Panda under different boxes and smooth-sign scales.

The case of ``tests/test_real_arm_workflow.py::test_coupled_containment_on_the_panda``:
a 3 s move (home -> target -> home, 1.5 s minimum-jerk segments), exact coupled RMI,
and the true plant at all 2^8 mass/payload corners (friction at a random corner each)
plus ``--draws`` uniform draws of every parameter. Per configuration: SPEC section 7's
containment (samples inside, clean runs, worst violation as a share of the width),
clean runs among the corners and among the draws apart, and where the worst sample is.

Configurations (``--configs``, each ``box:scale[:window]``): ``box`` is ``default``
(:func:`rmijax.default_box`), ``generic`` (:data:`rmijax.io.REAL_ARM_BOX`: 0-0.5 on
every joint) or ``none`` (no friction parameters); ``scale`` is the smooth sign's
velocity scale in rad/s (the library's constant is set for the run); ``window`` the RMI
window (default 100).

Run from the repository root (about a minute per configuration on 2 cores):

    python benchmarks/arm_containment.py --json benchmarks/results/arm_containment_cpu.json
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from _common import run_meta, table, write_json  # noqa: E402

DEFAULT_CONFIGS = ("generic:0.01", "generic:0.1", "none:0.1", "default:0.1")

COLUMNS = [
    ("box", "box", "{:>8s}"),
    ("smooth_sign_scale", "v_s rad/s", "{:>9.3g}"),
    ("window", "N", "{:>4d}"),
    ("inside", "inside", "{:>8.4%}"),
    ("clean_runs", "clean runs", "{:>10.1%}"),
    ("clean_corners", "clean corners", "{:>13.1%}"),
    ("clean_draws", "clean draws", "{:>11.1%}"),
    ("worst", "worst / width", "{:>13.1%}"),
    ("worst_output", "worst at (joint, sensor, t s)", "{:>29s}"),
]


def true_robots(params, draws, seed=0):
    """The test's true robots: every mass/payload corner, then uniform draws, (R, p)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(params.lo), np.asarray(params.hi)
    enumerated = 8  # 7 mass scales and the payload lead the parameter order
    index = np.arange(2**enumerated)
    bits = np.zeros((index.size, lo.size), bool)
    bits[:, :enumerated] = (index[:, None] >> np.arange(enumerated)[None, :]) & 1
    bits[:, enumerated:] = rng.integers(0, 2, (index.size, lo.size - enumerated))
    uniform = lo + (hi - lo) * rng.uniform(size=(draws, lo.size))
    return np.concatenate([np.where(bits, hi, lo), uniform])


def friction_hi(box):
    """The Coulomb upper bounds of a box, one per joint (empty without friction), N m."""
    import numpy as np

    if "friction" not in box:
        return []
    return [float(v) for v in np.broadcast_to(box["friction"]["coulomb"], (7, 2))[:, 1]]


def measure(box, scale, window, draws):
    import numpy as np

    import rmijax
    import rmijax.robots.spatial as spatial
    from rmijax.apps.real_arm import home_pose
    from rmijax.robots.loaders import REAL_ARM_BOX

    spatial.COULOMB_VELOCITY = scale  # read when the dynamics are traced
    kwargs = {
        "default": rmijax.default_box("panda"),
        "generic": REAL_ARM_BOX,
        "none": dict(mass=0.1, payload=(0.0, 1.0)),
    }[box]
    params = rmijax.load_robot("panda", **kwargs)
    home = home_pose("panda")
    target = home + np.array([0.45, 0.4, 0.0, 0.45, 0.0, 0.0, 0.5])
    traj = rmijax.waypoint_trajectory([home, target, home], segment_time=1.5)
    started = time.perf_counter()
    bounds = rmijax.rmi(traj, params, window=window)
    states, _ = rmijax.simulate(traj, params, true_robots(params, draws))
    seconds = time.perf_counter() - started
    corners = 2**8
    found = rmijax.containment(states, bounds)
    x = np.asarray(states)
    lower, upper = np.asarray(bounds.lower)[None], np.asarray(bounds.upper)[None]
    violation = np.maximum(np.maximum(lower - x, x - upper), 0.0)
    width = np.broadcast_to(upper - lower, x.shape)
    relative = np.where(width > 0, violation / np.where(width > 0, width, 1.0), 0.0)
    run, step, joint, sensor = np.unravel_index(np.argmax(relative), relative.shape)
    return dict(
        box=box,
        smooth_sign_scale=scale,
        window=window,
        coulomb_hi=friction_hi(kwargs),
        **found,
        clean_corners=rmijax.containment(states[:corners], bounds)["clean_runs"],
        clean_draws=rmijax.containment(states[corners:], bounds)["clean_runs"],
        worst_output=f"({joint + 1}, {'enc' if sensor == 0 else 'tach'}, "
        f"{float(step) * float(traj.dt):.2f})",
        worst_run_is_corner=bool(run < corners),
        seconds=seconds,
    )


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configs", nargs="+", default=list(DEFAULT_CONFIGS))
    parser.add_argument("--draws", type=int, default=200, help="uniform draws (200)")
    parser.add_argument("--json", default=None, help="write results here")
    args = parser.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    records = []
    for config in args.configs:
        box, scale, *rest = config.split(":")
        records.append(measure(box, float(scale), int(rest[0]) if rest else 100, args.draws))
        print(table(records[-1:], COLUMNS), flush=True)
    print(table(records, COLUMNS))
    meta = {**run_meta("benchmarks/arm_containment.py", argv, dtype="float64"), "args": vars(args)}
    write_json(args.json, records, meta)
    print(f"load average {meta['load_avg']}")
    return records


if __name__ == "__main__":
    main()
