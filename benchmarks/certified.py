"""Benchmark of the certified bands: time, tightness against the worst case, soundness counts.

For each case:

- time: one call with compile (``seconds``) and a second call (``seconds_warm``);
- soundness: all ``2^p`` corners (``p <= 12``) and ``--draws`` uniform draws run by
  ``rmijax.simulate``, and the ``worst_case`` maximisers at the scored times; the
  count of samples outside the band by more than 1e-12;
- tightness: band width / worst-case range (``rmijax.worst_case_table``) at
  times every ``--every`` s after 0.5 s, median and p90 per sensor (and the
  minimum, which must not fall below 1).

Example::

    PYTHONPATH=src python3 benchmarks/certified.py --cases arm2_hold_sine --duration 15 \\
        --json benchmarks/results/certified_cpu.json
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from _common import run_meta  # noqa: E402

import rmijax  # noqa: E402
from rmijax.methods.certified import certified_bounds  # noqa: E402

CASES = {
    "arm2_hold_sine": (rmijax.paper_arm2, ["hold", "sine"]),
    "arm2_hold_ramp": (rmijax.paper_arm2, ["hold", "ramp"]),
    "arm2_hold_composite": (rmijax.paper_arm2, ["hold", "composite"]),
    "arm2_slow_sine_composite": (rmijax.paper_arm2, ["slow_sine", "composite"]),
    "pendulum_sine": (rmijax.paper_pendulum, ["sine"]),
    "preset4_sine": (lambda: rmijax.preset_arm(4), ["sine"] * 4),
    "preset6_sine": (lambda: rmijax.preset_arm(6), ["sine"] * 6),
}


def _samples(params, draws, seed=0):
    lo, hi = np.asarray(params.lo), np.asarray(params.hi)
    rows = [lo + (hi - lo) * np.random.default_rng(seed).uniform(size=(draws, lo.size))]
    if params.n_params <= 12:
        rows.insert(0, np.asarray(params.corners))
    return np.concatenate(rows)


def run_case(name, duration, draws, every, splits):
    builder, paths = CASES[name]
    params = builder()
    traj = rmijax.trajectory(paths, duration=duration)
    start = time.perf_counter()
    bounds, cert = certified_bounds(traj, params, splits=splits)
    bounds.upper.block_until_ready()
    seconds = time.perf_counter() - start
    start = time.perf_counter()
    again, _ = certified_bounds(traj, params, splits=splits)
    again.upper.block_until_ready()
    seconds_warm = time.perf_counter() - start
    upper, lower = np.asarray(bounds.upper), np.asarray(bounds.lower)
    times = np.arange(0.5, duration + 1e-9, every)
    steps = np.round(times / traj.dt).astype(int)
    escapes, total = 0, 0
    worst = -np.inf
    samples = _samples(params, draws)
    seen_high = np.full(upper[steps].shape, -np.inf)
    seen_low = np.full(upper[steps].shape, np.inf)
    for chunk in np.array_split(samples, max(1, len(samples) // 256)):
        states = np.asarray(rmijax.simulate(traj, params, chunk)[0])
        out = np.maximum(states - upper, lower - states)
        escapes += int(np.sum(np.any(out > 1e-12, axis=(1, 2, 3))))
        total += len(chunk)
        worst = max(worst, float(out.max()))
        seen_high = np.maximum(seen_high, states[:, steps].max(0))
        seen_low = np.minimum(seen_low, states[:, steps].min(0))
    table = rmijax.worst_case_table(traj, params, times, random_starts=2, iterations=20)
    assert np.array_equal(steps, table["steps"])
    p = params.n_params
    maximisers = np.concatenate([table["th_low"].reshape(-1, p), table["th_high"].reshape(-1, p)])
    states = np.asarray(rmijax.simulate(traj, params, maximisers)[0])
    out = np.maximum(states - upper, lower - states)
    wc_escapes = int(np.sum(np.any(out > 1e-12, axis=(1, 2, 3))))
    worst = max(worst, float(out.max()))
    reach_high = np.maximum.reduce([table["high"], states[:, steps].max(0), seen_high])
    reach_low = np.minimum.reduce([table["low"], states[:, steps].min(0), seen_low])
    ratio = (upper[steps] - lower[steps]) / (reach_high - reach_low)
    row = dict(
        case=name,
        n=params.n_joints,
        pieces=int(cert.n_pieces),
        steps=traj.n_steps,
        seconds=round(seconds, 2),
        seconds_warm=round(seconds_warm, 2),
        samples=total,
        samples_outside=escapes,
        maximisers=len(maximisers),
        maximisers_outside=wc_escapes,
        worst_excess=worst,
    )
    for sensor, label in enumerate(("encoder", "tachometer")):
        r = ratio[..., sensor]
        row[f"{label}_median"] = round(float(np.median(r)), 3)
        row[f"{label}_p90"] = round(float(np.quantile(r, 0.9)), 3)
        row[f"{label}_min"] = round(float(np.min(r)), 3)
    return row


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=list(CASES)[:4], choices=list(CASES))
    parser.add_argument("--duration", type=float, default=15.0, help="run length in s")
    parser.add_argument("--draws", type=int, default=1000, help="uniform parameter draws")
    parser.add_argument("--every", type=float, default=0.5, help="scored times, every s")
    parser.add_argument("--splits", type=int, default=None, help="mass splits (default: auto)")
    parser.add_argument("--json", help="write the results to this JSON file")
    args = parser.parse_args(argv)
    rows = []
    header = (
        f"{'case':26} {'n':>2} {'pcs':>4} {'time s':>8} {'out/samples':>12} {'out/wc':>7} "
        f"{'enc med':>8} {'enc p90':>8} {'tach med':>8} {'tach p90':>8}"
    )
    print(header, flush=True)
    for name in args.cases:
        row = run_case(name, args.duration, args.draws, args.every, args.splits)
        rows.append(row)
        print(
            f"{name:26} {row['n']:>2} {row['pieces']:>4} {row['seconds']:>8.1f} "
            f"{row['samples_outside']:>5}/{row['samples']:<6} {row['maximisers_outside']:>3}/"
            f"{row['maximisers']:<3} {row['encoder_median']:>8} {row['encoder_p90']:>8} "
            f"{row['tachometer_median']:>8} {row['tachometer_p90']:>8}",
            flush=True,
        )
        if args.json:
            _write(args, rows)
    return rows


def _write(args, rows):
    record = dict(meta=run_meta("benchmarks/certified.py", dtype="float64"), rows=rows)
    with open(args.json, "w") as handle:
        json.dump(record, handle, indent=1)


if __name__ == "__main__":
    main()
