"""Where a certified band's width goes: the Taylor polynomial, its range bound, the remainder.

``certified_bounds`` gives, per piece of the box, ``x_c + range(S d + 1/2 Q[d, d]) +
[-r_k, r_k]`` (plus noise bounds, zero here), and the band is the union over pieces.
This script certifies one case and splits the band's width over the range of the
sampled runs (corners and uniform draws, as ``benchmarks/certified.py`` samples them;
a lower bound of the worst case) into three nested widths, per step from 0.5 s, joint
and sensor:

- ``poly_sampled``: the union over pieces of the Taylor polynomial's values at 3000
  points of each piece (1500 random corners, 1500 uniform draws): a lower bound of the
  polynomial's own range, so what the second-order model itself spreads over;
- ``poly_bound``: the union of the sound range bound of the polynomial that the band
  uses (``_poly_range``: each one-dimensional quadratic exactly, each cross term by its
  interval, summed);
- ``band``: the certified band (``poly_bound`` widened by each piece's remainder radius).

and ``remainder_share``: ``2 r_k`` of the widest piece over the band's width, and
``remainder_seen``: the largest ``|x_k(th) - (x_c + S d + 1/2 Q[d, d])|`` over the
sampled runs in a piece (a lower bound of the true remainder) over that piece's ``r_k``
(per step from 0.5 s, joint and piece). Read
``poly_bound / poly_sampled`` as the loss of the polynomial's range bound, and ``band /
poly_bound`` as what the remainder radius adds; more pieces shrink both, a tighter
remainder bound only the second. Not a timing benchmark: ``seconds`` is the
certificate's wall time, compile included.

Run from the repository root (about 10 minutes on 2 cores for the UR5e's box in 4):

    python benchmarks/certified_share.py --cases ur5e_box --split payload_mass=4 \\
        --json benchmarks/results/certified_share_cpu.json
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(pathlib.Path(__file__).parent))

import jax.numpy as jnp  # noqa: E402
from _common import run_meta  # noqa: E402
from certified import CASES, _samples, _split_items, _taylor_values, _trajectory  # noqa: E402

import rmijax  # noqa: E402
from rmijax.methods.certified import _poly_range, certified_bounds  # noqa: E402

POINTS = 3000  # polynomial evaluations per piece: half random corners, half uniform draws


def _hull_width(lows, highs):
    """Width of the hull over the leading (piece) axis."""
    return np.max(highs, axis=0) - np.min(lows, axis=0)


def _median_p90(values):
    values = values[~np.isnan(values)]  # NaN: an output no sampled run moved
    return [round(float(np.median(values)), 3), round(float(np.percentile(values, 90)), 3)]


def share_row(name, duration, splits, coulomb="auto", seed=0):
    """Certify ``name`` over ``duration`` s cut by ``splits``; the nested widths over the
    sampled range, median and p90 over steps from 0.5 s, joints (and pieces' ``r``)."""
    build, paths = CASES[name]
    params = build()
    traj = _trajectory(paths, duration)
    start = time.perf_counter()
    bounds, cert = certified_bounds(traj, params, splits=splits, coulomb=coulomb)
    bounds.upper.block_until_ready()
    seconds = round(time.perf_counter() - start, 1)

    samples = _samples(params, 1000)
    runs = np.concatenate(
        [
            np.asarray(rmijax.simulate(traj, params, chunk)[0])
            for chunk in np.array_split(samples, max(1, len(samples) // 256))
        ]
    )
    sampled = runs.max(0) - runs.min(0)  # (T+1, n, 2)

    state, sens, sens2 = (np.asarray(a) for a in (cert.state, cert.sens, cert.sens2))
    radius = np.asarray(cert.remainder)
    center, lo, hi = (np.asarray(a) for a in (cert.center, cert.lo, cert.hi))
    pieces, p = center.shape
    rng = np.random.default_rng(seed)
    poly_lo, poly_hi, bound_lo, bound_hi, seen = [], [], [], [], []
    first = int(round(0.5 / traj.dt))
    for i in range(pieces):
        d_lo, d_hi = lo[i] - center[i], hi[i] - center[i]
        inside = np.all((samples >= lo[i]) & (samples <= hi[i]), axis=1)
        if inside.any():  # the sampled runs' distance from this piece's polynomial
            model = _taylor_values(cert, i, samples[inside] - center[i])
            seen.append(np.abs(runs[inside] - model).max(0)[first:] / radius[i][first:])
        u = rng.random((POINTS, p))
        u[: POINTS // 2] = np.round(u[: POINTS // 2])  # random corners
        values = _taylor_values(cert, i, d_lo + u * (d_hi - d_lo))
        poly_lo.append(values.min(0))
        poly_hi.append(values.max(0))
        low, high = _poly_range(*(jnp.asarray(a) for a in (sens[i], sens2[i], d_lo, d_hi)))
        bound_lo.append(state[i] + np.asarray(low))
        bound_hi.append(state[i] + np.asarray(high))
    widths = dict(
        poly_sampled=_hull_width(poly_lo, poly_hi),
        poly_bound=_hull_width(bound_lo, bound_hi),
        band=np.asarray(bounds.upper) - np.asarray(bounds.lower),
    )
    row = dict(
        case=name,
        duration=duration,
        splits=splits,
        coulomb=coulomb,
        pieces=int(pieces),
        samples=len(samples),
        seconds=seconds,
    )
    for s, sensor in ((0, "encoder"), (1, "tachometer")):
        moved = sampled[first:, :, s] > 0
        for key, width in widths.items():
            ratio = width[first:, :, s] / np.where(moved, sampled[first:, :, s], np.nan)
            row[f"{sensor}_{key}"] = _median_p90(ratio)
        share = 2.0 * radius.max(0)[first:, :, s] / widths["band"][first:, :, s]
        row[f"{sensor}_remainder_share"] = _median_p90(share)
        row[f"{sensor}_remainder_seen"] = _median_p90(np.stack(seen)[..., s])
    return row


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=["ur5e_box"], choices=list(CASES))
    parser.add_argument("--duration", type=float, default=1.0, help="run length in s")
    parser.add_argument(
        "--split",
        nargs="+",
        default=[],
        metavar="NAME=PARTS",
        help="parts per named parameter, e.g. payload_mass=4 (default: the method's)",
    )
    parser.add_argument("--json", default=None, help="write the results to this JSON file")
    args = parser.parse_args(argv)
    try:
        splits = _split_items(args.split) or None
    except ValueError:
        parser.error(f"--split takes NAME=PARTS items, got {args.split}")
    rows = []
    for name in args.cases:
        rows.append(share_row(name, args.duration, splits))
        print(json.dumps(rows[-1]), flush=True)
        if args.json:
            meta = run_meta("benchmarks/certified_share.py", dtype="float64")
            record = dict(meta=meta, rows=rows)
            with open(args.json, "w") as handle:
                json.dump(record, handle, indent=1)


if __name__ == "__main__":
    main()
