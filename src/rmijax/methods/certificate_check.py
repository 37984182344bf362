"""An independent checker of a :class:`rmijax.methods.certified.Certificate` (``mpmath.iv``).

:func:`check_certificate` re-derives, step by step, every inequality that the
certified band rests on, with ``mpmath``'s outward-rounded interval
arithmetic (53-bit, each operation rounded outward by the library) instead of
the JAX float64 code that produced the certificate. It trusts nothing in the
certificate but uses its numbers as the *claims* to verify:

1. the pieces tile the box (a product grid whose cuts start at ``lo`` and end
   at ``hi``), and each centre lies in its piece;
2. the start: ``x_c(0) = x_d(0)``, ``S_0 = 0``, ``Q_0 = 0``;
3. for every checked step ``k``: the exact coefficients ``c0, c1, c2`` of the
   next Taylor model (the closed loop applied to the stored one, ``gv``'s jets
   at the centre) are enclosed, and the stored ``x_c(k+1), S_{k+1}, Q_{k+1}``
   differ from them by at most the rounding part; with the Lagrange remainder
   of ``gv`` over the tube that ``r_k`` defines, the stored input bound ``w_k``
   is at least the recomputed one;
4. ``r_{k+1} >= sum_{j <= k} |A^(k-j)| w_j`` with the powers of ``A`` in
   interval arithmetic (no truncation);
5. the band ``[lower_k, upper_k]`` holds every piece's enclosure
   ``x_c + range(S d + 1/2 Q[d, d]) + [-r_k, r_k] + [V_lo, V_hi]``.

Together these are the induction of :mod:`rmijax.methods.certified`, so a certificate
that passes for steps ``0..K`` proves the band for those steps. It is slow
(pure Python intervals: about a second per step and piece for two joints),
meant for short runs. It shares with the certifier only the formula of the
perturbation (:func:`rmijax.methods.certified.planar_perturbation_jets`) and the
jet's chain rule (:class:`rmijax._intervals.Jet`), both run here on
``mpmath`` intervals.

Requires ``mpmath`` (the ``test`` extra).
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import numpy as np

from rmijax._intervals import Jet
from rmijax.methods.certified import planar_perturbation_jets

__all__ = ["CheckResult", "check_certificate"]


class CheckResult(NamedTuple):
    """Outcome of :func:`check_certificate`.

    Attributes:
        ok: True when every checked inequality holds.
        steps: steps ``k`` whose band was verified (``0..steps-1``).
        reason: the first failed check, or "" when ok.
    """

    ok: bool
    steps: int
    reason: str


def _iv():
    try:
        from mpmath import iv
    except ImportError as error:  # pragma: no cover - mpmath is in the test extra
        raise ImportError("check_certificate needs mpmath (pip install 'rmijax[test]')") from error
    iv.prec = 53
    return iv


class _MpBackend:
    def __init__(self, iv):
        self.iv = iv

    def sin(self, x):
        return self.iv.sin(x)

    def cos(self, x):
        return self.iv.cos(x)

    def recip(self, x):
        return 1 / x

    def sqr(self, x):
        return x**2

    def is_interval(self, x):
        return isinstance(x, (self.iv.mpf, np.ndarray))

    def zeros(self, shape, like=None):
        return np.full(shape, self.iv.mpf(0), dtype=object)

    def outer(self, a, b):
        return np.multiply.outer(a, b)

    def point(self, value):
        return self.iv.mpf(float(value))


def _arr(iv, values):
    """An object array of point intervals from a float array."""
    values = np.asarray(values, np.float64)
    out = np.empty(values.shape, dtype=object)
    for index in np.ndindex(values.shape):
        out[index] = iv.mpf(float(values[index]))
    return out


def _mag(x):
    return abs(x).b


def _jets(backend, values, grads, hessians):
    return [Jet(values[i], grads[i], hessians[i], backend) for i in range(len(values))]


def _evaluate(backend, iv, state, grad_d, sens2, th, noise, consts, p, n, noisy):
    """``gv`` jets (lists) in the variables (d, R[, eta]); state etc. object arrays."""
    m = p + 2 * n + (2 * n if noisy else 0)
    zero, one = iv.mpf(0), iv.mpf(1)
    q, qd = [], []
    for i in range(n):
        for s, target in ((0, q), (1, qd)):
            grad = np.full(m, zero, dtype=object)
            grad[:p] = grad_d[i, s]
            grad[p + 2 * i + s] = one
            hess = np.full((m, m), zero, dtype=object)
            hess[:p, :p] = sens2[i, s]
            target.append(Jet(state[i, s], grad, hess, backend))
    th_jets = []
    for b in range(p):
        grad = np.full(m, zero, dtype=object)
        grad[b] = one
        th_jets.append(Jet(th[b], grad, np.full((m, m), zero, dtype=object), backend))
    noise_jets = None
    if noisy:
        eq, eqd = [], []
        for i in range(n):
            for s, target in ((0, eq), (1, eqd)):
                grad = np.full(m, zero, dtype=object)
                grad[p + 2 * n + 2 * i + s] = one
                target.append(Jet(noise[i, s], grad, np.full((m, m), zero, dtype=object), backend))
        noise_jets = (eq, eqd)
    return planar_perturbation_jets(
        q, qd, th_jets, consts["nominal"], consts["u"], consts["kp"], consts["kd"], noise_jets
    )


def _poly_range(iv, sens, sens2, d_box):
    """Enclosure of ``s' d + 1/2 d' Q d`` over the box (object arrays (p,), (p, p))."""
    p = len(d_box)
    total = iv.mpf(0)
    for b in range(p):
        s, c = sens[b], sens2[b][b] / 2
        lo, hi = iv.mpf(d_box[b].a), iv.mpf(d_box[b].b)
        values = [s * lo + c * lo**2, s * hi + c * hi**2]
        if not (c.a == 0 and c.b == 0):
            vertex = -s / (2 * c)
            if vertex.b >= d_box[b].a and vertex.a <= d_box[b].b:
                values.append(-(s**2) / (4 * c))
        low = min(v.a for v in values)
        high = max(v.b for v in values)
        total = total + iv.mpf([low, high])
    for a in range(p):
        for b in range(a + 1, p):
            total = total + (sens2[a][b] + sens2[b][a]) / 2 * (d_box[a] * d_box[b])
    return total


def _tiling_error(cert, params):
    lo, hi = np.asarray(params.lo, np.float64), np.asarray(params.hi, np.float64)
    plo, phi = np.asarray(cert.lo, np.float64), np.asarray(cert.hi, np.float64)
    centers = np.asarray(cert.center, np.float64)
    p = lo.size
    cuts = []
    for b in range(p):
        values = np.unique(np.concatenate([plo[:, b], phi[:, b]]))
        if values[0] != lo[b] or values[-1] != hi[b]:
            return f"the pieces do not span parameter {b}'s box [{lo[b]!r}, {hi[b]!r}]"
        cuts.append(values)
    cells = {tuple(row) for row in np.concatenate([plo, phi], axis=1)}
    count = 1
    for b in range(p):
        count *= max(len(cuts[b]) - 1, 1)
    grid = itertools.product(
        *[list(zip(c[:-1], c[1:], strict=True)) if len(c) > 1 else [(c[0], c[0])] for c in cuts]
    )
    for cell in grid:
        key = tuple(e[0] for e in cell) + tuple(e[1] for e in cell)
        if key not in cells:
            return f"no piece covers the cell {key} of the box"
    if np.any((centers < plo) | (centers > phi)):
        return "a piece's centre lies outside the piece"
    return ""


def check_certificate(cert, traj, params, *, steps: int | None = None, pieces=None) -> CheckResult:
    """Re-verify a certificate with outward-rounded ``mpmath`` interval arithmetic.

    Args:
        cert: the :class:`~rmijax.methods.certified.Certificate` of
            :func:`rmijax.methods.certified.certified_bounds` for ``traj`` and ``params``.
        traj, params: the run and the robot it certifies.
        steps: verify the band at steps ``0..steps`` (default: the whole run; a
            few dozen steps take a minute for two joints).
        pieces: indices of the pieces to verify (default: all).

    Returns:
        :class:`CheckResult`; ``ok`` is False with the first failed check in ``reason``.
    """
    if (cert.enclosure, cert.propagate) != ("interval", "kernel"):
        raise NotImplementedError(
            "check_certificate re-verifies certificates made with enclosure='interval' and "
            f"propagate='kernel' only, got {cert.enclosure!r} and {cert.propagate!r}: the "
            "affine enclosure and the carried generators have no independent checker yet"
        )
    iv = _iv()
    backend = _MpBackend(iv)
    n, p = traj.n_joints, params.n_params
    total = int(np.asarray(cert.state).shape[1]) - 1
    steps = total if steps is None else min(int(steps), total)
    reason = _tiling_error(cert, params)
    if reason:
        return CheckResult(False, 0, reason)
    dt = float(traj.dt)
    kp = [float(v) for v in np.asarray(traj.kp)]
    kd = [float(v) for v in np.asarray(traj.kd)]
    u_all = np.asarray(traj.u_d, np.float64)
    x0 = np.asarray(traj.x_n, np.float64)[0]
    nominal = [iv.mpf(float(v)) for v in np.asarray(params.nominal)]
    noise_lo = np.asarray(cert.noise_lo, np.float64)
    noise_hi = np.asarray(cert.noise_hi, np.float64)
    noisy = bool(np.any(noise_lo != 0) or np.any(noise_hi != 0))
    segments = int(cert.segments)
    lower, upper = np.asarray(cert.lower, np.float64), np.asarray(cert.upper, np.float64)
    # powers of every joint's A: A^m, m = 0..steps (interval matrices)
    a_mat = [
        np.array(
            [[iv.mpf(1), iv.mpf(dt)], [-iv.mpf(kp[i]) * dt, 1 - iv.mpf(kd[i]) * dt]], dtype=object
        )
        for i in range(n)
    ]
    powers = [
        [np.array([[iv.mpf(1), iv.mpf(0)], [iv.mpf(0), iv.mpf(1)]], dtype=object)] for _ in range(n)
    ]
    for i in range(n):
        for _ in range(steps):
            powers[i].append(a_mat[i].dot(powers[i][-1]))
    chosen = range(cert.n_pieces) if pieces is None else pieces
    for piece in chosen:
        state = np.asarray(cert.state[piece], np.float64)
        sens = np.asarray(cert.sens[piece], np.float64)
        sens2 = np.asarray(cert.sens2[piece], np.float64)
        injected = np.asarray(cert.injected[piece], np.float64)
        remainder = np.asarray(cert.remainder[piece], np.float64)
        center = np.asarray(cert.center[piece], np.float64)
        th_box = np.array(
            [
                iv.mpf([float(a), float(b)])
                for a, b in zip(cert.lo[piece], cert.hi[piece], strict=True)
            ],
            dtype=object,
        )
        d_box = th_box - _arr(iv, center)
        d_rad = [_mag(d) for d in d_box]
        if not (np.array_equal(state[0], x0) and not sens[0].any() and not sens2[0].any()):
            return CheckResult(False, 0, f"piece {piece}: the model does not start at x_d(0)")
        if np.any(remainder < 0) or np.any(injected < 0):
            return CheckResult(False, 0, f"piece {piece}: a negative remainder bound")
        for k in range(steps + 1):
            # 5. the band at step k
            for i in range(n):
                for s in range(2):
                    enclosure = (
                        iv.mpf(float(state[k, i, s]))
                        + _poly_range(iv, _arr(iv, sens[k, i, s]), _arr(iv, sens2[k, i, s]), d_box)
                        + iv.mpf([-float(remainder[k, i, s]), float(remainder[k, i, s])])
                        + iv.mpf([float(noise_lo[i, s]), float(noise_hi[i, s])])
                    )
                    if not (enclosure.a >= lower[k, i, s] and enclosure.b <= upper[k, i, s]):
                        return CheckResult(
                            False,
                            k,
                            f"piece {piece}, step {k}, joint {i} sensor {s}: the band "
                            f"[{lower[k, i, s]!r}, {upper[k, i, s]!r}] does not hold the "
                            f"enclosure {enclosure}",
                        )
            if k == steps:
                break
            # 4. the remainder bound of step k+1 from the inputs w_0..w_k
            for i in range(n):
                for s in range(2):
                    bound = iv.mpf(0)
                    for j in range(k + 1):
                        power = powers[i][k - j]
                        bound = bound + _mag(power[s, 0]) * float(injected[j, i, 0])
                        bound = bound + _mag(power[s, 1]) * float(injected[j, i, 1])
                    if not bound.b <= remainder[k + 1, i, s]:
                        return CheckResult(
                            False,
                            k,
                            f"piece {piece}, step {k + 1}: remainder bound "
                            f"{remainder[k + 1, i, s]!r} "
                            f"below sum |A^m| w = {bound}",
                        )
            # 3. the inputs w_k
            reason = _check_step(
                iv,
                backend,
                k,
                state,
                sens,
                sens2,
                injected,
                remainder,
                center,
                th_box,
                d_box,
                d_rad,
                u_all[k],
                nominal,
                kp,
                kd,
                dt,
                noise_lo,
                noise_hi,
                noisy,
                segments,
                n,
                p,
            )
            if reason:
                return CheckResult(False, k, f"piece {piece}, step {k}: {reason}")
    return CheckResult(True, steps, "")


def _check_step(
    iv,
    backend,
    k,
    state,
    sens,
    sens2,
    injected,
    remainder,
    center,
    th_box,
    d_box,
    d_rad,
    u,
    nominal,
    kp,
    kd,
    dt,
    noise_lo,
    noise_hi,
    noisy,
    segments,
    n,
    p,
):
    consts = dict(
        nominal=nominal,
        u=[iv.mpf(float(v)) for v in u],
        kp=[iv.mpf(v) for v in kp],
        kd=[iv.mpf(v) for v in kd],
    )
    zero = iv.mpf(0)
    xc, s1, s2 = _arr(iv, state[k]), _arr(iv, sens[k]), _arr(iv, sens2[k])
    noise0 = np.full((n, 2), zero, dtype=object) if noisy else None
    centre = _evaluate(backend, iv, xc, s1, s2, _arr(iv, center), noise0, consts, p, n, noisy)
    m = p + 2 * n + (2 * n if noisy else 0)
    rhat = [float(v) for v in remainder[k].reshape(-1)]
    eta_hat = [
        max(abs(a), abs(b)) for a, b in zip(noise_lo.reshape(-1), noise_hi.reshape(-1), strict=True)
    ]
    v_hat = list(d_rad) + rhat + (eta_hat if noisy else [])
    # the Lagrange remainder: Hessians over the nested boxes (j / J) Z
    spread = [np.full((m, m), zero, dtype=object) for _ in range(n)]
    noise_box = np.array(
        [
            [
                iv.mpf([min(float(noise_lo[i, s]), 0.0), max(float(noise_hi[i, s]), 0.0)])
                for s in range(2)
            ]
            for i in range(n)
        ],
        dtype=object,
    )
    for j in range(segments):
        s_hi = iv.mpf(j + 1) / segments
        s_lo = iv.mpf(j) / segments
        weight = (s_hi - s_lo) - (s_hi**2 - s_lo**2) / 2
        sd = d_box * s_hi
        tube = np.empty((n, 2), dtype=object)
        grad_d = np.empty((n, 2, p), dtype=object)
        for i in range(n):
            for s in range(2):
                tube[i, s] = (
                    xc[i, s]
                    + _poly_range(iv, s1[i, s], s2[i, s], sd)
                    + iv.mpf([-rhat[2 * i + s], rhat[2 * i + s]]) * s_hi
                )
                grad_d[i, s] = s1[i, s] + s2[i, s].dot(sd)
        th = _arr(iv, center) + sd
        box = _evaluate(
            backend,
            iv,
            tube,
            grad_d,
            s2,
            th,
            noise_box * s_hi if noisy else None,
            consts,
            p,
            n,
            noisy,
        )
        for i in range(n):
            diff = box[i].h.copy()
            diff[:p, :p] = diff[:p, :p] - centre[i].h[:p, :p]
            for a in range(m):
                for b in range(m):
                    spread[i][a, b] = spread[i][a, b] + iv.mpf(_mag(diff[a, b])) * weight
    for i in range(n):
        w = iv.mpf(0)
        for a in range(p, m):
            w = w + iv.mpf(_mag(centre[i].g[a])) * v_hat[a]
        for a in range(m):
            for b in range(m):
                w = w + spread[i][a, b] * (iv.mpf(v_hat[a]) * v_hat[b])
        # the next model against the exact coefficients c0, c1, c2
        q, qd = xc[i, 0], xc[i, 1]
        c0 = (q + qd * dt, qd + ((consts["u"][i] - qd * kd[i] - q * kp[i]) + centre[i].v) * dt)
        c1q = s1[i, 0] + s1[i, 1] * dt
        c1d = s1[i, 1] + (s1[i, 1] * (-kd[i]) + s1[i, 0] * (-kp[i]) + centre[i].g[:p]) * dt
        c2q = s2[i, 0] + s2[i, 1] * dt
        c2d = s2[i, 1] + (s2[i, 1] * (-kd[i]) + s2[i, 0] * (-kp[i]) + centre[i].h[:p, :p]) * dt
        for s, (a0, a1, a2) in enumerate(((c0[0], c1q, c2q), (c0[1], c1d, c2d))):
            err = iv.mpf(_mag(a0 - float(state[k + 1, i, s])))
            for b in range(p):
                err = err + iv.mpf(_mag(a1[b] - float(sens[k + 1, i, s, b]))) * d_rad[b]
                for c in range(p):
                    err = err + iv.mpf(_mag(a2[b, c] - float(sens2[k + 1, i, s, b, c]))) * (
                        iv.mpf(d_rad[b]) * d_rad[c] / 2
                    )
            need = err + (w * dt if s == 1 else 0)
            if not need.b <= injected[k, i, s]:
                return (
                    f"joint {i} sensor {s}: the remainder input {injected[k, i, s]!r} is below "
                    f"the recomputed bound {need}"
                )
    return ""
