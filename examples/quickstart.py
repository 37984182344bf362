"""Quickstart: RMI thresholds for the paper's two-joint arm, and a true run inside them.

Run: python examples/quickstart.py [--out quickstart.png]
"""

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)  # this script chooses float64

import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import rmijax  # noqa: E402


def true_run(traj, params, th_true):
    """The true closed loop with constant parameters th_true: states (T+1, n, 2)."""
    gv = jax.vmap(
        lambda x, u: rmijax.coupled_perturbation(
            params.model, th_true, params.nominal, x[:, 0], x[:, 1], u, traj.kp, traj.kd
        )
    )

    def step(x, u):
        g = gv(x[None], u[None])[0]
        q, qd = rmijax.closed_loop_step(x[:, 0], x[:, 1], u, g, traj.kp, traj.kd, traj.dt)
        nxt = jnp.stack([q, qd], -1)
        return nxt, nxt

    _, rest = jax.lax.scan(step, traj.x_n[0], traj.u_d[:-1])
    return jnp.concatenate([traj.x_n[:1], rest])


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

    th_true = params.nominal * jnp.array([1.08, 1.08, 1.0, 1.0]) - jnp.array([0, 0, 0.005, 0.005])
    states = true_run(traj, params, th_true)  # the paper's true robot
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
