"""Throughput of the spatial arm dynamics: batched M + h and the linear terms, per shipped arm.

Run from the repository root (float64, CPU):

    python benchmarks/dynamics.py --json benchmarks/results/dynamics_cpu.json

For each shipped arm (loaded with mass scales, a payload and both friction
kinds, so ``p = 3n + 1``), one ``jit(vmap)`` over ``--batch`` (state,
parameter) pairs computes ``M`` and ``h`` together; another computes the linear
terms (``M0, M_b (p, n, n), h0, h_b (p, n)`` per state) for the same states in the form
the exact search calls, ``terms_tracks_last`` (all states at once, states last).
Compile time is the first call; the throughput is ``batch / median`` of
``--calls`` calls after one warm-up call (p99 reported too).
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).parent))

from _common import run_meta, table, time_calls, write_json  # noqa: E402

from rmijax.robots.loaders import SHIPPED, load_robot  # noqa: E402

COLUMNS = [
    ("robot", "robot", "{:>7}"),
    ("n_joints", "n", "{:>2d}"),
    ("n_params", "p", "{:>3d}"),
    ("compile_s", "compile M+h s", "{:>13.2f}"),
    ("pairs_per_s", "M+h pairs/s", "{:>11,.0f}"),
    ("p99_us_per_pair", "p99 us/pair", "{:>11.2f}"),
    ("terms_compile_s", "compile terms s", "{:>15.2f}"),
    ("terms_per_s", "terms states/s", "{:>14,.0f}"),
]


def _compiled(fn, args):
    started = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - started


def measure(name, batch, calls, seed=0):
    """Compile times and throughput of one arm, as a record."""
    robot = load_robot(
        name, mass=0.2, payload=(0.0, 3.0), friction=dict(viscous=(0.0, 1.0), coulomb=(0.0, 1.0))
    )
    model, n = robot.model, robot.n_joints
    rng = np.random.default_rng(seed)
    q = rng.uniform(-np.pi, np.pi, (batch, n))
    qd = rng.normal(size=(batch, n))
    lo, hi = np.asarray(robot.lo), np.asarray(robot.hi)
    th = lo + (hi - lo) * rng.uniform(size=(batch, lo.size))
    both = jax.jit(jax.vmap(lambda q, qd, th: (model.mass_matrix(q, th), model.bias(q, qd, th))))
    terms = jax.jit(lambda q, qd: model.structure.terms_tracks_last(q.T, qd.T))
    compile_s = _compiled(both, (q, qd, th))
    timing = time_calls(both, lambda i: (q, qd, th), calls=calls)
    terms_compile_s = _compiled(terms, (q, qd))
    terms_timing = time_calls(terms, lambda i: (q, qd), calls=calls)
    return dict(
        robot=name,
        n_joints=n,
        n_params=robot.n_params,
        batch=batch,
        compile_s=compile_s,
        pairs_per_s=batch / timing["p50_s"],
        p50_us_per_pair=1e6 * timing["p50_s"] / batch,
        p99_us_per_pair=1e6 * timing["p99_s"] / batch,
        terms_compile_s=terms_compile_s,
        terms_per_s=batch / terms_timing["p50_s"],
        terms_p99_us_per_state=1e6 * terms_timing["p99_s"] / batch,
    )


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", nargs="+", default=list(SHIPPED), choices=SHIPPED)
    parser.add_argument("--batch", type=int, default=4096, help="pairs per call (4096)")
    parser.add_argument("--calls", type=int, default=20, help="timed calls per function (20)")
    parser.add_argument("--json", metavar="PATH", help="write the records and machine here")
    args = parser.parse_args(argv)
    records = [measure(name, args.batch, args.calls) for name in args.robots]
    print(table(records, COLUMNS))
    meta = {**run_meta("benchmarks/dynamics.py", argv, dtype="float64"), "args": vars(args)}
    write_json(args.json, records, meta)
    print(f"device: {meta['device']}; load average {meta['load_avg']}")
    return records


if __name__ == "__main__":
    main()
