"""A slow, plainly written NumPy reference of SPEC sections 1 and 3-5.

Written independently of the JAX engine: the mass matrix comes straight from
the triple sum of section 1, the Coriolis terms from Christoffel symbols of
its analytic derivative, the coupled mode carries the full ``2n`` state with a
block-diagonal ``A`` and a full-state costate, and everything loops over end
steps, outputs and window steps. Only the corner axis is vectorised.
"""

from __future__ import annotations

import numpy as np

GRAVITY = 9.81


class PlanarArmNumpy:
    """``M``, ``h`` of the planar point-mass arm for a stack of parameter vectors."""

    def __init__(self, n):
        self.n = n
        idx = np.arange(n)
        # mask[i, j, k, a, b] = 1 when k >= max(i, j), i <= a <= k, j <= b <= k.
        i, j, k, a, b = np.meshgrid(idx, idx, idx, idx, idx, indexing="ij")
        self.mask = ((k >= np.maximum(i, j)) & (a >= i) & (a <= k) & (b >= j) & (b <= k)).astype(
            float
        )
        ii, kk, aa = np.meshgrid(idx, idx, idx, indexing="ij")
        self.gravity_mask = ((kk >= ii) & (aa >= ii) & (aa <= kk)).astype(float)  # [i, k, a]

    def _coef(self, th):
        th = np.atleast_2d(th)
        m, l = th[:, : self.n], th[:, self.n :]
        # coef[K, i, j, a, b] = sum_k m_k mask[i,j,k,a,b] * l_a l_b
        return np.einsum("ck,ijkab,ca,cb->cijab", m, self.mask, l, l)

    def mass_matrix(self, q, th):
        """(K, n, n) from the triple sum ``sum_k m_k sum_a sum_b l_a l_b cos(phi_a - phi_b)``."""
        phi = np.cumsum(q)
        cos = np.cos(phi[:, None] - phi[None, :])
        return np.einsum("cijab,ab->cij", self._coef(th), cos)

    def mass_matrix_derivative(self, q, th):
        """(K, n, n, n): ``dM_ij / dq_r``."""
        n = self.n
        phi = np.cumsum(q)
        sin = np.sin(phi[:, None] - phi[None, :])
        idx = np.arange(n)
        # d phi_a / d q_r = [r <= a]
        dphi = (idx[None, :] <= idx[:, None]).astype(float)  # [a, r]
        dcos = -sin[:, :, None] * (dphi[:, None, :] - dphi[None, :, :])  # [a, b, r]
        return np.einsum("cijab,abr->cijr", self._coef(th), dcos)

    def bias(self, q, qd, th):
        """(K, n): ``h = C(q, qd) qd + G(q)`` with Christoffel symbols of ``M``."""
        th = np.atleast_2d(th)
        dm = self.mass_matrix_derivative(q, th)
        # (C qd)_i = sum_jk (dM_ij/dq_k - 1/2 dM_jk/dq_i) qd_j qd_k
        coriolis = np.einsum("cijk,j,k->ci", dm, qd, qd) - 0.5 * np.einsum(
            "cjki,j,k->ci", dm, qd, qd
        )
        m, l = th[:, : self.n], th[:, self.n :]
        phi = np.cumsum(q)
        gravity = GRAVITY * np.einsum("ck,ika,ca,a->ci", m, self.gravity_mask, l, np.cos(phi))
        return coriolis + gravity


def problem_args(traj, params):
    """``(q_d, qd_d, qdd_d, kp, kd, dt, nominal)`` of rmijax objects, as NumPy arguments."""
    arrays = (traj.q_d, traj.qd_d, traj.qdd_d, traj.kp, traj.kd)
    return (*(np.asarray(a) for a in arrays), traj.dt, np.asarray(params.nominal))


def pick(score, offset, largest):
    """First corner whose score is within the tie tolerance of the best one.

    Scores equal up to roundoff are ties (SPEC section 2: lowest index wins);
    the tolerance is eps^(2/3) relative to ``max|score| + |offset|``.
    """
    tol = np.finfo(float).eps ** (2.0 / 3.0) * (np.abs(score).max() + abs(offset))
    if largest:
        return np.flatnonzero(score >= score.max() - tol)[0]
    return np.flatnonzero(score <= score.min() + tol)[0]


def corners_of(lo, hi):
    p = len(lo)
    rows = []
    for c in range(2**p):
        rows.append([hi[b] if (c >> b) & 1 else lo[b] for b in range(p)])
    return np.array(rows, dtype=float)


def closed_loop(q_d, qd_d, qdd_d, kp, kd, dt):
    """Feed-forward, nominal state (T+1, n, 2) and nominal acceleration."""
    n_samples, n = q_d.shape
    u_d = qdd_d + kd * qd_d + kp * q_d
    x_n = np.zeros((n_samples, n, 2))
    x_n[0, :, 0], x_n[0, :, 1] = q_d[0], qd_d[0]
    for k in range(n_samples - 1):
        for i in range(n):
            a = np.array([[1.0, dt], [-kp[i] * dt, 1.0 - kd[i] * dt]])
            b = np.array([0.0, dt])
            x_n[k + 1, i] = a @ x_n[k, i] + b * u_d[k, i]
    qdd_n = u_d - kd * x_n[..., 1] - kp * x_n[..., 0]
    return u_d, x_n, qdd_n


def rmi_reference(
    model,
    q_d,
    qd_d,
    qdd_d,
    kp,
    kd,
    dt,
    nominal,
    lo,
    hi,
    *,
    mode,
    window,
    v_lo=None,
    v_hi=None,
    end_steps=None,
):
    """Bounds (lower, upper, nominal), each (T+1, n, 2), by SPEC sections 3-5 verbatim.

    ``end_steps`` limits the work to those end steps (the others stay zero).
    """
    n_samples, n = q_d.shape
    v_lo = np.zeros((n, 2)) if v_lo is None else np.broadcast_to(v_lo, (n, 2))
    v_hi = np.zeros((n, 2)) if v_hi is None else np.broadcast_to(v_hi, (n, 2))
    kp, kd = np.broadcast_to(kp, (n,)).astype(float), np.broadcast_to(kd, (n,)).astype(float)
    corners = corners_of(lo, hi)
    u_d, x_n, qdd_n = closed_loop(q_d, qd_d, qdd_d, kp, kd, dt)
    a_joint = [np.array([[1.0, dt], [-kp[i] * dt, 1.0 - kd[i] * dt]]) for i in range(n)]
    a_full = np.zeros((2 * n, 2 * n))
    for i in range(n):
        a_full[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] = a_joint[i]
    velocity_rows = np.arange(n) * 2 + 1

    def torque(q, qd, u):
        v = u - kd * qd - kp * q
        tau = model.mass_matrix(q, nominal)[0] @ v + model.bias(q, qd, nominal)[0]
        return v, tau

    def gv_coupled(x, u):  # x (2n,) -> (K, n)
        q, qd = x[0::2], x[1::2]
        v, tau = torque(q, qd, u)
        mh = model.mass_matrix(q, corners)
        hh = model.bias(q, qd, corners)
        qdd = np.linalg.solve(mh, (tau[None, :] - hh)[..., None])[..., 0]
        return qdd - v[None, :]

    def gv_per_joint(i, xi, k):  # joint i's own state xi (2,) at step k -> (K,)
        q, qd = x_n[k, :, 0].copy(), x_n[k, :, 1].copy()
        q[i], qd[i] = xi
        v, tau = torque(q, qd, u_d[k])
        mh = model.mass_matrix(q, corners)
        hh = model.bias(q, qd, corners)
        others = sum(mh[:, i, j] * qdd_n[k, j] for j in range(n) if j != i)
        return (tau[i] - others - hh[:, i]) / mh[:, i, i] - v[i]

    lower = np.zeros((n_samples, n, 2))
    upper = np.zeros((n_samples, n, 2))
    for t_f in range(n_samples) if end_steps is None else end_steps:
        k0 = max(0, t_f - window)
        for i in range(n):
            for s in range(2):
                if mode == "coupled":
                    c = np.zeros(2 * n)
                    c[2 * i + s] = 1.0
                    costate = {t_f: c}
                    for k in range(t_f - 1, k0, -1):
                        costate[k] = a_full.T @ costate[k + 1]
                else:
                    c = np.eye(2)[s]
                    costate = {t_f: c}
                    for k in range(t_f - 1, k0, -1):
                        costate[k] = a_joint[i].T @ costate[k + 1]
                result = []
                for largest in (True, False):
                    if mode == "coupled":
                        x = x_n[k0].reshape(-1).copy()
                        for k in range(k0, t_f):
                            gv = gv_coupled(x, u_d[k])
                            weight = costate[k + 1][velocity_rows]
                            score = gv @ weight
                            v_i = u_d[k, i] - kd[i] * x[2 * i + 1] - kp[i] * x[2 * i]
                            chosen = gv[pick(score, weight[i] * v_i, largest)]
                            b_u = np.zeros(2 * n)
                            b_u[velocity_rows] = dt * u_d[k] + dt * chosen
                            x = a_full @ x + b_u
                        result.append(x[2 * i + s])
                    else:
                        x = x_n[k0, i].copy()
                        for k in range(k0, t_f):
                            gv = gv_per_joint(i, x, k)
                            score = costate[k + 1][1] * gv
                            v_i = u_d[k, i] - kd[i] * x[1] - kp[i] * x[0]
                            chosen = gv[pick(score, costate[k + 1][1] * v_i, largest)]
                            x = (
                                a_joint[i] @ x
                                + np.array([0.0, dt]) * u_d[k, i]
                                + np.array([0.0, dt]) * chosen
                            )
                        result.append(x[s])
                upper[t_f, i, s] = result[0] + v_hi[i, s]
                lower[t_f, i, s] = result[1] + v_lo[i, s]
    return lower, upper, x_n


def simulate_faults(model, q_d, qd_d, qdd_d, kp, kd, dt, nominal, th_true, faults, noise):
    """Plain plant simulation with faults (SPEC section 7): true states and readings (T+1, n, 2).

    ``faults`` are ``(kind, joint, onset_step, value, sensor)`` tuples; ``noise``
    is the (T+1, n, 2) noise added to healthy readings.
    """
    n_samples, n = q_d.shape
    u_d = qdd_d + kd * qd_d + kp * q_d
    x = np.zeros((n_samples, n, 2))
    y = np.zeros((n_samples, n, 2))
    x[0, :, 0], x[0, :, 1] = q_d[0], qd_d[0]
    held = {}
    for k in range(n_samples):
        state = x[k].copy()
        locked = [j for (kind, j, on, _, _) in faults if kind == "locked" and k >= on]
        for j in locked:
            state[j, 1] = 0.0
        x[k] = state
        reading = state + noise[k]
        for kind, j, on, _value, _sensor in faults:
            if k < on:
                continue
            outputs = {"stuck_encoder": [0], "stuck_tach": [1], "stuck_sensors": [0]}.get(kind, [])
            for s in outputs:
                if k == on:
                    held[(j, s)] = reading[j, s]
                reading[j, s] = held[(j, s)]
            if kind == "stuck_sensors":
                reading[j, 1] = 0.0
        for kind, j, on, value, sensor in faults:
            if k >= on and kind == "bias":
                reading[j, sensor] += value
            if k >= on and kind == "drift":
                reading[j, sensor] += value * (k * dt - on * dt)
        y[k] = reading
        if k == n_samples - 1:
            break
        q, qd = state[:, 0], state[:, 1]
        qm, qdm = reading[:, 0], reading[:, 1]
        v = u_d[k] - kd * qdm - kp * qm
        tau = model.mass_matrix(qm, nominal)[0] @ v + model.bias(qm, qdm, nominal)[0]
        for kind, j, on, _, _ in faults:
            if kind == "free_swinging" and k >= on:
                tau[j] = 0.0
        mass = model.mass_matrix(q, th_true)[0]
        rhs = tau - model.bias(q, qd, th_true)[0]
        free = [j for j in range(n) if j not in locked]
        qdd = np.zeros(n)
        qdd[free] = np.linalg.solve(mass[np.ix_(free, free)], rhs[free])
        x[k + 1, :, 0] = q + dt * qd
        x[k + 1, :, 1] = qd + dt * qdd
    return x, y
