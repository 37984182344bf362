"""A monitored control loop: plant, computed-torque controller and RMI monitor in one lax.scan.

A two-joint arm (the paper's, with every mass x1.08 and every length -5 mm) follows
joint 1 `hold`, joint 2 `sine`. At 5 s both sensors of joint 2 stick (the encoder
freezes, the tachometer reads 0). Each tick the monitor gets the desired feed-forward
and the readings and says whether they are inside the RMI bands.

Run: python examples/control_loop.py [--out control_loop.png]
"""

import argparse

import jax

jax.config.update("jax_enable_x64", True)  # this script chooses float64

import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import rmijax  # noqa: E402

ONSET_S = 5.0
FAULTY_JOINT = 1  # 0-based: the paper's joint 2


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="control_loop.png", help="figure path (PNG)")
    args = parser.parse_args()

    params = rmijax.paper_arm2()
    traj = rmijax.trajectory(["hold", "sine"], duration=8.0)  # desired path, gains, dt
    th_true = rmijax.experiments.paper_true_parameters(params)
    kp, kd, dt = traj.kp, traj.kd, traj.dt
    mon = rmijax.monitor(params, kp=kp, kd=kd, dt=dt)  # coupled RMI, window 100
    onset = round(ONSET_S / dt)

    def tick(carry, inputs):
        x, held, state = carry  # true state (n, 2), held faulty reading, monitor state
        k, q_d, qd_d, qdd_d = inputs
        # Sensors: joint 2's encoder freezes at onset, its tachometer reads 0.
        held = jnp.where(k == onset, x[FAULTY_JOINT, 0], held)
        reading = x.at[FAULTY_JOINT].set(
            jnp.where(k >= onset, jnp.array([held, 0.0]), x[FAULTY_JOINT])
        )
        # The monitor checks this tick's readings.
        state, out = mon.update(state, (q_d, qd_d, qdd_d), reading)
        # The computed-torque controller acts on the readings ...
        u_d = qdd_d + kd * qd_d + kp * q_d
        v = u_d - kd * reading[:, 1] - kp * reading[:, 0]
        tau = params.model.torques(reading[:, 0], reading[:, 1], v, params.nominal)
        # ... and the true robot moves under that torque from its true state.
        qdd = params.model.accelerations(x[:, 0], x[:, 1], tau, th_true)
        x = jnp.stack([x[:, 0] + dt * x[:, 1], x[:, 1] + dt * qdd], axis=-1)
        return (x, held, state), (out, reading)

    @jax.jit
    def run():
        state = mon.init(traj.q_d[0], traj.qd_d[0])
        inputs = (jnp.arange(traj.n_steps + 1), traj.q_d, traj.qd_d, traj.qdd_d)
        return jax.lax.scan(tick, (traj.x_n[0], 0.0, state), inputs)

    (_, _, state), (out, readings) = run()
    first = int(state.first_alarm)
    print(
        f"fault injected at tick {onset} ({ONSET_S:g} s); first alarm at tick {first} "
        f"({first * dt:.2f} s) on outputs {jnp.argwhere(out.alarm[first]).tolist()} "
        "[joint, sensor], 0-based"
    )

    fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    t = traj.t
    for sensor, (ax, unit) in enumerate(zip(axes, ["rad", "rad/s"], strict=True)):
        base = out.nominal[:, FAULTY_JOINT, sensor]
        ax.fill_between(
            t,
            out.lower[:, FAULTY_JOINT, sensor] - base,
            out.upper[:, FAULTY_JOINT, sensor] - base,
            alpha=0.3,
            label="live RMI band",
        )
        ax.plot(t, readings[:, FAULTY_JOINT, sensor] - base, lw=1, label="reading")
        ax.axvline(ONSET_S, color="k", ls="--", lw=0.8, label="fault onset")
        ax.axvline(first * dt, color="tab:red", ls=":", lw=1.2, label="first alarm")
        width = float(jnp.max(out.upper - out.lower, axis=0)[FAULTY_JOINT, sensor])
        ax.set_ylim(-1.5 * width, 1.5 * width)
        ax.set_ylabel(f"joint 2 {('encoder', 'tachometer')[sensor]} - nominal [{unit}]")
    axes[1].set_xlabel("time [s]")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
