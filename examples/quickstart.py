"""Quickstart: RMI thresholds for the paper's two-joint arm, and a true run inside them.

Run: python examples/quickstart.py [--out quickstart.png]
"""

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)  # this script chooses float64

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import rmijax  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="quickstart.png", help="figure path (PNG)")
    args = parser.parse_args()

    params = rmijax.paper_arm2()  # masses, lengths within boxes
    traj = rmijax.trajectory(["hold", "sine"])  # joint 1 holds, joint 2 sine, 15 s
    start = time.perf_counter()
    bounds = rmijax.rmi(traj, params)  # coupled mode, window 100
    bounds.upper.block_until_ready()
    print(
        f"RMI bounds for {traj.n_steps + 1} steps in {time.perf_counter() - start:.2f} s "
        "(compile included)"
    )

    th_true = rmijax.experiments.paper_true_parameters(params)  # masses x1.08, lengths -5 mm
    states, _ = rmijax.simulate(traj, params, th_true)  # the true robot, no fault
    inside = (states >= bounds.lower - 1e-9) & (states <= bounds.upper + 1e-9)
    print(f"true run inside the bounds at {float(inside.mean()) * 100:.2f}% of samples")

    fig, axes = plt.subplots(2, 2, figsize=(11, 6), sharex=True)
    for joint in range(2):
        for sensor, unit in enumerate(["rad", "rad/s"]):
            ax = axes[sensor, joint]
            ax.fill_between(
                traj.t,
                bounds.lower[:, joint, sensor] - bounds.nominal[:, joint, sensor],
                bounds.upper[:, joint, sensor] - bounds.nominal[:, joint, sensor],
                alpha=0.3,
                label="RMI band",
            )
            ax.plot(
                traj.t,
                states[:, joint, sensor] - bounds.nominal[:, joint, sensor],
                lw=1,
                label="true run",
            )
            ax.set_title(f"joint {joint + 1} {'encoder' if sensor == 0 else 'tachometer'}")
            ax.set_ylabel(f"deviation from nominal [{unit}]")
    for ax in axes[1]:
        ax.set_xlabel("time [s]")
    axes[0, 0].legend()
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
