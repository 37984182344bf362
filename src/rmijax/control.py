"""Computed-torque control and the explicit-Euler closed loop (SPEC sections 3-4).

Per joint the closed loop is ``x_i(k+1) = A_i x_i(k) + B_i u_d,i(k) + dt e2 gv_i(k)``
with ``A_i = [[1, dt], [-Kp dt, 1 - Kd dt]]``, ``B_i = [0, dt]'`` and the
perturbation ``gv = qdd - v``, which vanishes when the true parameters equal
the nominal ones. These helpers are shared by the nominal trajectory, the RMI
engine and the plant simulation so that all three step the same way.
"""

from __future__ import annotations

__all__ = [
    "closed_loop_step",
    "computed_torque",
    "coupled_perturbation",
    "feedforward",
    "servo_command",
]


def feedforward(q_d, qd_d, qdd_d, kp, kd):
    """``u_d = qdd_d + Kd qd_d + Kp q_d`` (rad/s^2), any leading shape ``(..., n)``."""
    return qdd_d + kd * qd_d + kp * q_d


def servo_command(q, qd, u_d, kp, kd):
    """Commanded acceleration ``v = u_d - Kd qd - Kp q`` (rad/s^2), shape ``(n,)``."""
    return u_d - kd * qd - kp * q


def computed_torque(model, nominal, q, qd, v):
    """Controller torque ``tau = M(q; th_n) v + h(q, qd; th_n)`` (N m), shape ``(n,)``."""
    return model.torques(q, qd, v, nominal)


def coupled_perturbation(model, th, nominal, q, qd, u_d, kp, kd):
    """``gv = M(q; th)^-1 (tau - h(q, qd; th)) - v`` for the measured state ``(q, qd)``.

    Args:
        model: the :class:`~rmijax.robots.model.RobotModel`.
        th: true parameters (p,).
        nominal: the controller's parameters ``th_n`` (p,).
        q, qd: joint positions (rad) and velocities (rad/s), (n,).
        u_d: feed-forward (n,).
        kp, kd: gains (n,).

    Returns:
        gv (n,) in rad/s^2: true acceleration minus commanded acceleration.
    """
    v = servo_command(q, qd, u_d, kp, kd)
    tau = computed_torque(model, nominal, q, qd, v)
    return model.accelerations(q, qd, tau, th) - v


def closed_loop_step(q, qd, u_d, gv, kp, kd, dt):
    """One explicit-Euler step ``x(k+1) = A x(k) + B u_d(k) + dt e2 gv(k)``.

    All arguments broadcast elementwise (per joint). Returns ``(q_next, qd_next)``.
    """
    q_next = q + dt * qd
    qd_next = ((-kp * dt) * q + (1.0 - kd * dt) * qd + dt * u_d) + dt * gv
    return q_next, qd_next
