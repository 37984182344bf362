"""How far float32 RMI bounds are from float64 ones, relative to the band width.

For each case (arm, paths, mode) the whole run is computed in both dtypes; the error
of a sample is ``|b32 - b64|`` over the widest float64 band of that output, taken over
upper and lower bounds. The issue on scaling asks for 1e-5 before float32 can be
recommended.

Run: python benchmarks/precision.py [--json PATH]
"""

from __future__ import annotations

import argparse
import pathlib
import sys

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _common import run_meta, table, write_json  # noqa: E402

CASES = [
    (2, ("hold", "sine"), 15.0),
    (2, ("slow_sine", "composite"), 15.0),
    (3, ("slow_sine", "sine", "sine"), 4.0),
    (4, ("slow_sine", "sine", "sine", "sine"), 4.0),
]

COLUMNS = [
    ("n", "n", "{:>2d}"),
    ("paths", "paths", "{:>30s}"),
    ("mode", "mode", "{:>9s}"),
    ("max_error", "max err", "{:>9.2e}"),
    ("median_error", "median err", "{:>10.2e}"),
    ("share_above", "share > 1e-5", "{:>12.3f}"),
]


def measure(n, paths, duration, mode):
    import jax.numpy as jnp
    import numpy as np

    import rmijax

    bounds = {}
    for dtype in (jnp.float64, jnp.float32):
        traj = rmijax.trajectory(list(paths), duration=duration, dtype=dtype)
        bounds[dtype] = rmijax.rmi(traj, rmijax.preset_arm(n, dtype=dtype), mode=mode)
    b64, b32 = bounds[jnp.float64], bounds[jnp.float32]
    scale = np.asarray(b64.width).max(axis=0)  # widest band of each output
    error = (
        np.maximum(
            np.abs(np.asarray(b32.upper, np.float64) - np.asarray(b64.upper)),
            np.abs(np.asarray(b32.lower, np.float64) - np.asarray(b64.lower)),
        )
        / scale
    )
    return {
        "n": n,
        "paths": ",".join(paths),
        "mode": mode,
        "max_error": float(error.max()),
        "median_error": float(np.median(error)),
        "share_above": float(np.mean(error > 1e-5)),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", default=None, help="write results here")
    args = parser.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    import rmijax

    records = []
    for n, paths, duration in CASES:
        for mode in rmijax.MODES:
            records.append(measure(n, paths, duration, mode))
            lines = table(records, COLUMNS).splitlines()
            print("\n".join(lines if len(records) == 1 else lines[-1:]), flush=True)
    meta = run_meta("benchmarks/precision.py", argv, dtype="float32 against float64")
    write_json(args.json, records, meta)
    print("error: |float32 - float64| over the widest float64 band of the output")


if __name__ == "__main__":
    main()
