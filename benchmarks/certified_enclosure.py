"""Why ``certified`` stops at two links: how wide its Hessian enclosure is, and what would help.

``certified`` bounds the remainder of its second-order Taylor model with the
spread of ``gv``'s Hessian (in the parameters) over the box, enclosed by interval
2-jets (:mod:`rmijax._intervals`). On ``preset_arm(4)`` and ``preset_arm(6)`` the
remainder diverges within the first 0.2 s. This script measures, at the start of
the run (state ``x_d(0)``, known exactly, so only the parameter box is uncertain),
per joint and in rad/s^2:

- ``first``: ``sum_a |dgv/dth_a| r_a`` at the nominal (the first-order effect);
- ``second``: ``sum_ab |H_ab(th_n)| r_a r_b`` (what the Taylor model carries);
- ``true``: ``sum_ab max_th |H_ab(th) - H_ab(th_n)| r_a r_b`` over all corners (up to
  4096) and 300 uniform draws: a *lower* bound of the quantity the certificate must
  bound (autodiff Hessians of the model's own ``M`` and ``h``);
- ``interval``: the same with the enclosure ``certified`` uses today;
- ``affine``: the same with a prototype *affine arithmetic* backend for the same jet
  formulas (numpy, written here; float rounding is **not** bounded, so this is a
  measurement of the dependency loss, not a certificate).

at the full box and at half and a quarter of it (what splitting the box buys).
Second, the induction's sensitivity to that enclosure: ``certified_bounds`` on
``preset_arm(4)`` (1 s; one piece, and each mass range in 2 parts: 16 pieces) with
``remainder_scale`` s = 1, 0.1, 0.01 (and 0.001 unsplit)
(the remainder's input multiplied by s; anything below 1 voids the guarantee and is
used here only to ask how much tighter the enclosure would have to be): the step at
which it diverges, or the largest remainder against the first-order range.

Run from the repository root (a few minutes on 2 cores):

    python benchmarks/certified_enclosure.py --json benchmarks/results/certified_enclosure_cpu.json

With ``--neumann`` (about 10 minutes on 2 cores) it measures instead what a bound without
a Hessian gives, where ``M`` is linear in the uncertain parameters: the exact second-order
remainder of ``gv`` in them bounded in joint coordinates and in the kinetic-energy norm
(``_mass_remainder``), against its sampled size, at four states each of ``preset_arm(2, 4,
6)`` (masses) and of the shipped arms under their default box:

    python benchmarks/certified_enclosure.py --neumann \\
        --json benchmarks/results/certified_neumann_cpu.json

With ``--blocks`` (under a minute) it splits ``certified``'s remainder input ``w_k`` by
source (``blocks_row``); with ``--tube`` (a few minutes) it sets the quadratic part of
``w_k`` against the same quantity from sampled Hessians over the certificate's own tube
(``tube_row``), which tells the enclosure's loss from the model's:

    python benchmarks/certified_enclosure.py --blocks \\
        --json benchmarks/results/certified_blocks_cpu.json
    python benchmarks/certified_enclosure.py --tube \\
        --json benchmarks/results/certified_tube_cpu.json

The ``--tube`` rows also give the same quantity from a prototype affine backend
(``_affine_hessian_box``). With ``--induction`` (about 3 minutes) it replays
``certified``'s induction for one piece in numpy with either enclosure, and with the
remainder propagated through the nominal loop (as ``certified``) or through the piece
centre's own linearised loop (``induction_row``): does the affine enclosure keep 4 links
bounded?

    python benchmarks/certified_enclosure.py --induction \\
        --json benchmarks/results/certified_induction_cpu.json

With ``--arms`` (a few minutes) it sets ``certified``'s remainder radius on the shipped
arms' whole default box against the true remainder of the same Taylor model, from sampled
runs (``arm_remainder_row``):

    python benchmarks/certified_enclosure.py --arms \\
        --json benchmarks/results/certified_arm_remainder_cpu.json

With ``--parts`` (about 15 minutes) it certifies each arm's move (``--duration``, 1 s)
under parts of that box (``BOX_PARTS``: with and without Coulomb friction, ...) and
records where each diverges (``box_part_row``):

    python benchmarks/certified_enclosure.py --parts \\
        --json benchmarks/results/certified_box_parts_cpu.json

With ``--union`` (about 15 minutes) every piece is replayed that way and the union of
their bands set against sampled constant-parameter runs (``union_row``):

    python benchmarks/certified_enclosure.py --union \\
        --json benchmarks/results/certified_union_cpu.json
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from _common import run_meta, table, write_json  # noqa: E402

import rmijax  # noqa: E402
from rmijax._intervals import Interval, Jet  # noqa: E402
from rmijax.control import coupled_perturbation  # noqa: E402
from rmijax.methods.base import DivergedError  # noqa: E402
from rmijax.methods.certified import (  # noqa: E402
    _certify_box,
    _evaluate,
    _kernel,
    _pieces,
    _poly_range,
    _split_counts,
    certified_bounds,
    planar_perturbation_jets,
)


# --------------------------------------------------------------------------
# A prototype affine-arithmetic backend (measurement only: no rounding bounds)
# --------------------------------------------------------------------------
class Affine:
    """``c + sum_i a_i eps_i + e [-1, 1]`` elementwise, ``eps_i`` in [-1, 1] shared.

    Keeps first-order dependencies between quantities that interval arithmetic
    forgets (each mass enters the articulated solve many times). Float rounding is
    not accounted for: a prototype to measure the enclosure, not to certify.
    """

    __array_priority__ = 1000

    def __init__(self, c, a, e):
        self.c, self.a, self.e = (np.asarray(v, float) for v in (c, a, e))

    @staticmethod
    def of(x, k):
        if isinstance(x, Affine):
            return x
        x = np.asarray(x, float)
        return Affine(x, np.zeros(x.shape + (k,)), np.zeros(x.shape))

    @property
    def k(self):
        return self.a.shape[-1]

    def rad(self):
        return np.sum(np.abs(self.a), -1) + self.e

    def bounds(self):
        r = self.rad()
        return self.c - r, self.c + r

    def __getitem__(self, i):
        return Affine(self.c[i], self.a[i], self.e[i])

    def __add__(self, o):
        o = Affine.of(o, self.k)
        return Affine(self.c + o.c, self.a + o.a, self.e + o.e)

    __radd__ = __add__

    def __neg__(self):
        return Affine(-self.c, -self.a, self.e)

    def __sub__(self, o):
        return self + (-Affine.of(o, self.k))

    def __rsub__(self, o):
        return Affine.of(o, self.k) - self

    def __mul__(self, o):
        if not isinstance(o, Affine):
            o = np.asarray(o, float)
            return Affine(self.c * o, self.a * o[..., None], self.e * np.abs(o))
        a = self.a * o.c[..., None] + o.a * self.c[..., None]
        e = np.abs(self.c) * o.e + np.abs(o.c) * self.e + self.rad() * o.rad()
        return Affine(self.c * o.c, a, e)

    __rmul__ = __mul__

    def __truediv__(self, o):
        return self * _affine_recip(Affine.of(o, self.k))

    def __rtruediv__(self, o):
        return Affine.of(o, self.k) * _affine_recip(self)


def _affine_recip(x):
    """Min-range linearisation of ``1/x`` (convex on a range that excludes 0)."""
    lo, hi = x.bounds()
    negative = hi < 0
    small, large = np.where(negative, -hi, lo), np.where(negative, -lo, hi)
    sign = np.where(negative, -1.0, 1.0)
    slope = -1.0 / large**2
    at_small, at_large = 1.0 / small - slope * small, 1.0 / large - slope * large
    offset, error = 0.5 * (at_small + at_large), 0.5 * np.abs(at_small - at_large)
    error = np.where((lo > 0) | (hi < 0), error, np.inf)
    return Affine(slope * x.c + sign * offset, slope[..., None] * x.a, np.abs(slope) * x.e + error)


def _affine_sqr(x):
    r = x.rad()
    return Affine(x.c**2 + 0.5 * r**2, 2 * x.c[..., None] * x.a, 2 * np.abs(x.c) * x.e + 0.5 * r**2)


def _affine_trig(x, fn, slope_fn):
    slope = slope_fn(x.c)
    return Affine(fn(x.c), slope[..., None] * x.a, np.abs(slope) * x.e + 0.5 * x.rad() ** 2)


class AffineBackend:
    """The operations :class:`rmijax._intervals.Jet` needs, on :class:`Affine` arrays."""

    def __init__(self, k):
        self.k = k

    sin = staticmethod(lambda x: _affine_trig(x, np.sin, np.cos))
    cos = staticmethod(lambda x: _affine_trig(x, np.cos, lambda c: -np.sin(c)))
    recip = staticmethod(_affine_recip)
    sqr = staticmethod(_affine_sqr)

    @staticmethod
    def is_interval(x):
        return isinstance(x, Affine)

    def zeros(self, shape, like=None):
        return Affine.of(np.zeros(shape), self.k)

    @staticmethod
    def outer(a, b):
        return a[:, None] * b[None, :]

    def point(self, value):
        return Affine.of(value, self.k)


# --------------------------------------------------------------------------
# The measurements
# --------------------------------------------------------------------------
def _start(n):
    params = rmijax.preset_arm(n)
    traj = rmijax.trajectory(["sine"] * n, duration=1.0)
    return params, traj


def _gv_function(params, traj):
    model, nominal = params.model, jnp.asarray(params.nominal)
    x, u, kp, kd = traj.x_n[0], traj.u_d[0], traj.kp, traj.kd

    def gv(th):
        return coupled_perturbation(model, th, nominal, x[:, 0], x[:, 1], u, kp, kd)

    return gv


def _interval_hessian(params, traj, lo, hi):
    n, p = params.n_joints, params.n_params
    consts = dict(nominal=params.nominal, u=traj.u_d[0], kp=traj.kp, kd=traj.kd)
    _, _, hessian = _evaluate(
        Interval(traj.x_n[0]),
        Interval(jnp.zeros((n, 2, p))),
        jnp.zeros((n, 2, p, p)),
        Interval(jnp.asarray(lo), jnp.asarray(hi)),
        None,
        consts,
    )
    return np.asarray(hessian.lo)[:, :p, :p], np.asarray(hessian.hi)[:, :p, :p]


def _affine_hessian(params, traj, lo, hi):
    n, p = params.n_joints, params.n_params
    backend = AffineBackend(p)
    x, u = np.asarray(traj.x_n[0]), np.asarray(traj.u_d[0])
    kp, kd = np.asarray(traj.kp), np.asarray(traj.kd)

    def constant(value):
        return Jet(backend.point(value), backend.zeros((p,)), backend.zeros((p, p)), backend)

    q = [constant(x[i, 0]) for i in range(n)]
    qd = [constant(x[i, 1]) for i in range(n)]
    centre, radius = 0.5 * (lo + hi), 0.5 * (hi - lo)
    th = []
    for b in range(p):
        th.append(
            Jet(
                Affine(centre[b], np.eye(p)[b] * radius[b], 0.0),
                backend.point(np.eye(p)[b]),
                backend.zeros((p, p)),
                backend,
            )
        )
    points = [[backend.point(v) for v in values] for values in (params.nominal, u, kp, kd)]
    gv = planar_perturbation_jets(q, qd, th, *points)
    return np.stack([j.h.bounds()[0] for j in gv]), np.stack([j.h.bounds()[1] for j in gv])


def enclosure_row(n, fraction, draws=300, seed=0):
    params, traj = _start(n)
    nominal = np.asarray(params.nominal)
    lo = nominal + (np.asarray(params.lo) - nominal) * fraction
    hi = nominal + (np.asarray(params.hi) - nominal) * fraction
    radius = 0.5 * (hi - lo)
    gv = _gv_function(params, traj)
    hessian = jax.jit(jax.vmap(jax.hessian(gv)))
    centre_h = np.asarray(jax.hessian(gv)(jnp.asarray(nominal)))
    corners = np.asarray(params.corners)[:4096]
    corners = nominal + (corners - nominal) * fraction
    uniform = lo + (hi - lo) * np.random.default_rng(seed).uniform(size=(draws, lo.size))
    samples = np.concatenate([corners, uniform])
    deviation = np.zeros_like(centre_h)
    for chunk in np.array_split(samples, -(-len(samples) // 256)):  # (one big batch hung XLA)
        values = np.asarray(jax.block_until_ready(hessian(jnp.asarray(chunk))))
        deviation = np.maximum(deviation, np.max(np.abs(values - centre_h), axis=0))

    def weighted(spread):
        return np.einsum("iab,a,b->i", spread, radius, radius)

    def spread_of(bounds):
        low, high = bounds
        return np.maximum(high - centre_h, centre_h - low)

    interval = weighted(spread_of(_interval_hessian(params, traj, lo, hi)))
    start = time.perf_counter()
    affine = weighted(spread_of(_affine_hessian(params, traj, lo, hi)))
    affine_seconds = time.perf_counter() - start
    true = weighted(deviation)
    first = np.abs(np.asarray(jax.jacfwd(gv)(jnp.asarray(nominal)))) @ radius
    return dict(
        links=n,
        box_fraction=fraction,
        samples=int(samples.shape[0]),
        first=first.tolist(),
        second=weighted(np.abs(centre_h)).tolist(),
        true=true.tolist(),
        interval=interval.tolist(),
        affine=affine.tolist(),
        interval_over_true_max=float(np.max(interval / true)),
        affine_over_true_max=float(np.max(affine / true)),
        affine_seconds=affine_seconds,
    )


def scale_row(splits, scale, duration):
    """``certified_bounds`` on ``preset_arm(4)`` with the remainder's input times ``scale``."""
    params, _ = _start(4)
    traj = rmijax.trajectory(["sine"] * 4, duration=duration)
    row = dict(links=4, splits=splits, pieces=splits**4, duration=duration, remainder_scale=scale)
    try:
        _, cert = certified_bounds(traj, params, splits=splits, remainder_scale=scale)
    except DivergedError as error:
        return row | dict(diverged_at_step=error.step, diverged_at_s=error.step * traj.dt)
    radius = 0.5 * (np.asarray(cert.hi) - np.asarray(cert.lo))  # (P, p)
    sens = np.abs(np.asarray(cert.sens)[:, :, :, 0, :])  # (P, T+1, n, p) encoder
    first = np.max(np.einsum("Pkip,Pp->Pki", sens, radius), axis=0)  # the widest piece
    remainder = np.max(np.asarray(cert.remainder)[:, :, :, 0], axis=0)  # (T+1, n) encoder
    return row | dict(
        diverged_at_step=None,
        max_encoder_remainder=np.max(remainder, axis=0).tolist(),
        max_first_order_range=np.max(first, axis=0).tolist(),
    )


def neumann_row(n, states=4, seed=0):
    """How far the mass box moves ``M`` relative to itself, and how well the exact
    second-order remainder of ``gv`` in the masses can be bounded without a Hessian.

    ``M`` is linear in the masses, ``M(th) = M_n (I + sum_k d_k M_n^-1 M_k)``, so
    ``|M_n^-1 (M(th) - M_n)| <= G = sum_k r_k |M_n^-1 M_k|`` elementwise for every
    mass in the box (lengths are left at nominal: ``M`` is not linear in them). A
    Neumann enclosure needs ``||D^-1 G D|| < 1`` for some positive diagonal ``D``; the
    smallest such norm is ``G``'s Perron root, the unscaled one the row-sum norm. At the
    start state of the sine run (``q = qd = 0``) and at ``states - 1`` uniform random
    states (``q`` in ``[-pi, pi]``, ``qd`` in ``[-1, 1]`` rad/s); the remainder bounds of
    ``_mass_remainder`` at each. Lists are per state, the start state first.
    """
    params, traj = _start(n)
    return dict(links=n, **_remainder_row(params, traj, list(range(n)), states, seed))


def real_arm_row(name, states=4, seed=0):
    """``neumann_row`` for a shipped arm under its default box (body mass scales,
    payload and friction, all varied: ``M`` and ``h`` are linear in every one), at the
    start of the real-arm job's pick-and-place move and ``states - 1`` random states."""
    from rmijax.apps.real_arm import real_arm_case

    case = real_arm_case(name)
    row = _remainder_row(case.params, case.traj, list(range(case.params.n_params)), states, seed)
    return dict(robot=name, links=case.params.n_joints, **row)


def _remainder_row(params, traj, varied, states, seed):
    n = params.n_joints
    radius = 0.5 * (np.asarray(params.hi) - np.asarray(params.lo))
    rng = np.random.default_rng(seed)
    x0 = np.asarray(traj.x_n[0])
    points = [(x0[:, 0], x0[:, 1])] + [
        (rng.uniform(-np.pi, np.pi, n), rng.uniform(-1.0, 1.0, n)) for _ in range(states - 1)
    ]
    rows = [_mass_remainder(params, traj, radius, varied, q, qd, seed) for q, qd in points]
    return dict(
        states=states,
        varied=[params.model.param_names[k] for k in varied],
        angles=[np.asarray(q).tolist() for q, _ in points],
        rates=[np.asarray(qd).tolist() for _, qd in points],
        **{key: [row[key] for row in rows] for key in rows[0]},
    )


def _mass_remainder(params, traj, radius, varied, q, qd, seed, draws=300):
    """At the state ``(q, qd)`` with the run's first servo command ``v``, the parameters
    ``varied`` over their box (the others at nominal): the exact second-order remainder
    of ``gv`` in them, ``-T (I + T)^-1 T w`` with ``T = M_n^-1 dM`` and ``w = M_n^-1 B d``
    (``M`` and ``M v + h`` linear in the varied parameters, checked), bounded two ways,
    against its sampled size and the first-order range (all rad/s^2, per joint).

    *Joint coordinates* (``bound_joint``): with ``G = sum_k r_k |M_n^-1 M_k|`` (Perron root
    below 1), ``|w| <= W = sum_k r_k |M_n^-1 B_k|``, ``|T y| <= G |y|`` and ``|(I + T)^-1
    z| <= (I - G)^-1 |z|``, so ``|rem| <= G (I - G)^-1 G W``.

    *Kinetic-energy norm* (``bound_energy``): every parameter's slope ``M_k = dM/dth_k``
    is positive semidefinite (checked: a mass, a body's inertia scale, a payload), so
    ``|x' dM x| <= x' (sum_k r_k M_k) x <= rho x' M_n x`` with ``rho`` the largest
    eigenvalue of ``L^-1 (sum_k r_k M_k) L^-T`` (``M_n = L L'``; 0.1 for masses +-10 %).
    ``T`` is self-adjoint in ``<x, y> = x' M_n y`` with spectrum in ``[-rho, rho]``, so
    ``||rem||_M <= rho^2 / (1 - rho) ||w||_M``, ``||w||_M <= sum_k r_k ||L^-1 B_k||``
    and ``|rem_i| <= sqrt((M_n^-1)_ii) ||rem||_M``. No absolute values of matrix entries,
    so nothing is lost along the chain. Both bounds are sound, so is their elementwise
    minimum (``bound_min``).

    Sampled: the corners of the parameters that move ``M`` (with the others at random
    corners; at most 4096) and ``draws`` uniform points, ``gv`` minus its second-order
    Taylor polynomial (autodiff of the model's own ``M`` and ``h``).
    """
    model, nominal = params.model, np.asarray(params.nominal)
    varied = np.asarray(varied)
    kp, kd, u = (np.asarray(a) for a in (traj.kp, traj.kd, traj.u_d[0]))
    v = jnp.asarray(u - kd * np.asarray(qd) - kp * np.asarray(q))
    q, qd = jnp.asarray(q), jnp.asarray(qd)

    def full(sub):
        return jnp.asarray(nominal).at[varied].set(sub)

    force = lambda sub: model.mass_matrix(q, full(sub)) @ v + model.bias(q, qd, full(sub))  # noqa: E731
    mass = lambda sub: model.mass_matrix(q, full(sub))  # noqa: E731
    centre = jnp.asarray(nominal[varied])
    r = radius[varied]
    m_n = np.asarray(mass(centre))
    inverse = np.linalg.inv(m_n)
    slopes = np.asarray(jax.jacfwd(mass)(centre))  # (n, n, varied): dM/dth_k
    columns = np.asarray(jax.jacfwd(force)(centre))  # (n, varied): B
    probe = centre + r * np.random.default_rng(seed + 1).uniform(-1, 1, r.size)
    for name, fn, slope in (("M", mass, slopes), ("M v + h", force, columns)):
        # tolerance in the function's own units: its size at the centre and over the box
        scale = float(np.max(np.abs(fn(centre))) + np.max(np.abs(slope)) * np.max(r))
        if not np.allclose(fn(probe), fn(centre) + slope @ (probe - centre), atol=1e-9 * scale):
            raise ValueError(f"{name} is not linear in the varied parameters: vary fewer")
    scale = float(np.max(np.abs(m_n)))
    least = min(float(np.min(np.linalg.eigvalsh(slopes[:, :, k]))) for k in range(r.size))
    if least < -1e-9 * scale:
        raise ValueError(f"a parameter's slope of M is not positive semidefinite ({least})")
    g = sum(r[k] * np.abs(inverse @ slopes[:, :, k]) for k in range(r.size))
    first = np.abs(inverse @ columns) @ r  # W: the first-order range per joint
    # y = (I + C dM)^-1 z solves y = z - C dM y, so |y| <= |z| + G |y| and, with the
    # Perron root of G below 1, |y| <= (I - G)^-1 |z| elementwise ((I - G)^-1 = sum G^k)
    perron = float(np.max(np.abs(np.linalg.eigvals(g))))
    bound_joint = (
        g @ np.linalg.solve(np.eye(g.shape[0]) - g, g @ first)
        if perron < 1
        else np.full(first.shape, np.inf)
    )
    cholesky = np.linalg.cholesky(m_n)
    spread = np.einsum("ijk,k->ij", slopes, r)
    whitened = np.linalg.solve(cholesky, np.linalg.solve(cholesky, spread).T)
    rho = float(np.max(np.linalg.eigvalsh(0.5 * (whitened + whitened.T))))
    w_norm = float(np.sum(r * np.linalg.norm(np.linalg.solve(cholesky, columns), axis=0)))
    bound_energy = (
        np.sqrt(np.diag(inverse)) * rho**2 / (1.0 - rho) * w_norm
        if rho < 1
        else np.full(first.shape, np.inf)
    )

    def gv(sub):
        return jnp.linalg.solve(mass(sub), force(centre) - force(sub))

    grad = np.asarray(jax.jacfwd(gv)(centre))
    hess = np.asarray(jax.hessian(gv)(centre))
    lo, hi = np.asarray(centre) - r, np.asarray(centre) + r
    rng = np.random.default_rng(seed)
    moving = np.flatnonzero(np.abs(slopes).max(axis=(0, 1)) > 0)[:12]
    signs = rng.integers(0, 2, size=(2**moving.size, r.size)).astype(float)
    signs[:, moving] = np.array(list(np.ndindex(*(2,) * moving.size)), float)
    uniform = rng.uniform(size=(draws, r.size))
    points = lo + (hi - lo) * np.concatenate([signs, uniform])
    d = points - np.asarray(centre)
    taylor = d @ grad.T + 0.5 * np.einsum("iab,sa,sb->si", hess, d, d)
    values = np.asarray(jax.jit(jax.vmap(gv))(jnp.asarray(points)))
    worst = np.max(np.abs(values - taylor), axis=0)
    return dict(
        row_sum_norm=float(np.max(g.sum(axis=1))),
        perron_root=perron,
        energy_rho=rho,
        first_order=first.tolist(),
        bound_joint=bound_joint.tolist(),
        bound_energy=bound_energy.tolist(),
        bound_min=np.minimum(bound_joint, bound_energy).tolist(),
        sampled=worst.tolist(),
    )


BLOCKS = ("linear", "mm", "ml", "mx", "lm", "ll", "lx", "xm", "xl", "xx")
"""The parts of ``w_k`` (``certified``'s ``w_blocks``): the first-order terms in the
remainder and noise, then the quadratic term by blocks of masses (m), lengths (l) and
remainder/noise (x)."""


def blocks_row(n, splits, duration, kernel_steps=400, segments=3):
    """Where ``certified``'s remainder input ``w_k`` comes from on ``preset_arm(n)``
    (sine on every joint, each parameter range in ``splits`` parts): per step until the
    bound diverges (or ``duration`` ends), the share of each block of ``BLOCKS`` in ``w_k``
    of the last joint's velocity, in the piece where ``w_k`` is largest."""
    params = rmijax.preset_arm(n)
    traj = rmijax.trajectory(["sine"] * n, duration=duration)
    zeros = jnp.zeros((n, 2))
    *_, pieces, _, _ = _certify_box(
        traj, params, zeros, zeros, splits, kernel_steps, segments, diagnostics=True
    )
    blocks = np.asarray(pieces["w_blocks"])[:, :, -1, :]  # (P, T, 10): last joint
    total = blocks.sum(axis=-1)  # (P, T)
    finite = np.isfinite(total).all(axis=0) & (total.max(axis=0) < 1e6)
    steps = int(np.argmin(finite)) if not finite.all() else total.shape[1]
    rows = []
    for k in range(steps):
        piece = int(np.argmax(total[:, k]))
        share = dict(zip(BLOCKS, (blocks[piece, k] / total[piece, k]).tolist(), strict=True))
        rows.append(dict(step=k, w=float(total[piece, k]), **share))
    return dict(links=n, splits=splits, duration=duration, steps=rows)


def _segments(segments):
    """``certified``'s radial segments ``[j/J, (j+1)/J]`` of the Lagrange remainder: their
    upper ends and weights ``int (1 - s) ds`` (floats, not rounded up: measurements)."""
    seg_hi = (np.arange(segments) + 1.0) / segments
    seg_lo = np.arange(segments) / segments
    return seg_hi, (seg_hi - seg_lo) - 0.5 * (seg_hi**2 - seg_lo**2)


def tube_row(n, splits, steps, duration=0.3, samples=1500, seed=0, segments=3):
    """How much of ``certified``'s remainder input the true Hessian needs, step by step.

    ``certified`` bounds ``w_k`` by the spread of the Hessian of ``z -> gv(x(z), th(z))``
    in ``z = (d, R)`` (``x = x_c + S_k d + 1/2 Q_k[d, d] + R``, ``th = th_c + d``), over
    the boxes ``s_j Z`` of its radial segments (``Z``: the piece's radii and ``|R| <=
    r_k``), enclosed by interval 2-jets and weighted by ``int (1 - s) ds``. Here the
    same quantity from samples: in each segment's box, ``samples`` uniform points and
    as many random corners, the entrywise largest ``|H(z) - H(0)|`` (autodiff of the
    model's own ``M`` and ``h``; a *lower* bound of the best entrywise enclosure over
    those boxes), weighted alike and summed by the blocks of :data:`BLOCKS` (masses,
    lengths, remainder). ``preset_arm(n)``, sine on every joint, the last joint's
    velocity, at each of ``steps`` in the piece where the certificate's ``w_k`` is
    largest; the tube is the certificate's own (its ``S_k``, ``Q_k`` and ``r_k``).
    """
    params = rmijax.preset_arm(n)
    traj = rmijax.trajectory(["sine"] * n, duration=duration)
    zeros = jnp.zeros((n, 2))
    centers, los, his, pieces, _, _ = _certify_box(
        traj, params, zeros, zeros, splits, segments=segments, diagnostics=True
    )
    blocks = np.asarray(pieces["w_blocks"])[:, :, -1, :]  # (P, T, 10): last joint
    model, nominal = params.model, jnp.asarray(params.nominal)
    kp, kd = traj.kp, traj.kd
    p = params.n_params
    m = p + 2 * n
    seg_hi, weights = _segments(segments)
    edges = (0, n, p, m)
    spans = list(zip(edges[:-1], edges[1:], strict=True))

    def last_joint_gv(z, xc, sens, sens2, center, u):
        d, rem = z[:p], z[p:].reshape(n, 2)
        x = xc + sens @ d + 0.5 * jnp.einsum("ijab,a,b->ij", sens2, d, d) + rem
        gv = coupled_perturbation(model, center + d, nominal, x[:, 0], x[:, 1], u, kp, kd)
        return gv[-1]

    hessian = jax.jit(
        jax.vmap(jax.hessian(last_joint_gv), in_axes=(0, None, None, None, None, None))
    )
    rng = np.random.default_rng(seed)
    rows = []
    for k in steps:
        piece = int(np.argmax(blocks[:, k].sum(axis=-1)))
        args = (jnp.asarray(pieces[key][piece, k]) for key in ("state", "sens", "sens2"))
        args = (*args, jnp.asarray(centers[piece]), traj.u_d[k])
        radius = 0.5 * (np.asarray(his[piece]) - np.asarray(los[piece]))
        rhat = np.asarray(pieces["remainder"][piece, k])
        v_hat = np.concatenate([radius, rhat.reshape(-1)])
        centre_h = np.asarray(hessian(jnp.zeros((1, m)), *args))[0]
        spread = np.zeros((m, m))
        for s_hi, weight in zip(seg_hi, weights, strict=True):
            points = np.concatenate(
                [rng.uniform(-1, 1, (samples, m)), rng.choice([-1.0, 1.0], (samples, m))]
            )
            worst = np.zeros((m, m))
            for chunk in np.array_split(points * v_hat * s_hi, -(-2 * samples // 256)):
                values = np.asarray(jax.block_until_ready(hessian(jnp.asarray(chunk), *args)))
                worst = np.maximum(worst, np.max(np.abs(values - centre_h), axis=0))
            spread += weight * worst
        quadratic = spread * np.outer(v_hat, v_hat)
        piece_data = {key: pieces[key][piece, k] for key in ("state", "sens", "sens2")}
        piece_data["center"] = centers[piece]
        affine_q = _affine_tube_spread(
            piece_data, radius, rhat, params, traj, k, seg_hi, weights
        ) * np.outer(v_hat, v_hat)
        affine = [float(affine_q[a0:a1, b0:b1].sum()) for a0, a1 in spans for b0, b1 in spans]
        attribution = _tube_attribution(pieces, piece, k, centers, los, his, params, traj)
        sampled = [float(quadratic[a0:a1, b0:b1].sum()) for a0, a1 in spans for b0, b1 in spans]
        interval = blocks[piece, k, 1:].tolist()
        rows.append(
            dict(
                step=k,
                piece=piece,
                remainder_max=float(rhat.max()),
                interval=dict(zip(BLOCKS[1:], interval, strict=True)),
                sampled=dict(zip(BLOCKS[1:], sampled, strict=True)),
                affine=dict(zip(BLOCKS[1:], affine, strict=True)),
                interval_total=float(sum(interval)),
                sampled_total=float(sum(sampled)),
                affine_total=float(sum(affine)),
                attribution=attribution,
            )
        )
    return dict(
        links=n,
        splits=splits,
        duration=duration,
        samples=2 * samples,
        segments=segments,
        steps=rows,
    )


def _affine_hessian_box(xc, sens, sens2, center, radius, rhat, scale, params, u, kp, kd):
    """Hessian of ``gv`` (every joint) in ``z = (d, R)`` over the box ``scale Z`` of the
    tube, by the prototype affine backend: ``(lo, hi)``, each (n, m, m).

    The state enters as affine forms in the same symbols as the parameters, ``x = x_c +
    S_k d + R`` exactly (the quadratic ``1/2 Q_k[d, d]`` as an error term), and its
    gradient in ``d`` as ``S_k + Q_k d``, so the first-order dependence of the state on
    the parameters, which interval arithmetic forgets, is kept. Rounding is not bounded
    (a measurement, not a certificate)."""
    n, p = xc.shape[0], params.n_params
    m = p + 2 * n
    backend = AffineBackend(m)
    points = [[backend.point(v) for v in values] for values in (params.nominal, u, kp, kd)]
    rad = np.concatenate([radius, np.reshape(rhat, -1)]) * scale  # symbol scales
    state = []
    for i in range(n):
        for s in range(2):
            unit = np.zeros(2 * n)
            unit[2 * i + s] = 1.0
            quad = 0.5 * np.sum(np.abs(sens2[i, s]) * np.outer(rad[:p], rad[:p]))
            value = Affine(xc[i, s], np.concatenate([sens[i, s], unit]) * rad, quad)
            grad_a = np.zeros((m, m))
            grad_a[:p, :p] = sens2[i, s] * rad[None, :p]
            hess = np.zeros((m, m))
            hess[:p, :p] = sens2[i, s]
            grad = Affine(np.concatenate([sens[i, s], unit]), grad_a, np.zeros(m))
            state.append(Jet(value, grad, backend.point(hess), backend))
    th = [
        Jet(
            Affine(center[b], np.eye(m)[b] * rad[b], 0.0),
            backend.point(np.eye(m)[b]),
            backend.zeros((m, m)),
            backend,
        )
        for b in range(p)
    ]
    gv = planar_perturbation_jets(state[0::2], state[1::2], th, *points)
    bounds = [jet.h.bounds() for jet in gv]
    return np.stack([b[0] for b in bounds]), np.stack([b[1] for b in bounds])


def _affine_tube_spread(piece_data, radius, rhat, params, traj, k, seg_hi, weights):
    """The certificate's weighted Hessian spread over the tube by the prototype affine
    backend (:func:`_affine_hessian_box`): ``sum_j weight_j max|H(z) - H(0)|`` over the
    boxes ``s_j Z`` for the last joint, an (m, m) array like the sampled one of
    :func:`tube_row`."""
    args = [np.asarray(piece_data[key]) for key in ("state", "sens", "sens2", "center")]
    consts = (np.asarray(traj.u_d[k]), np.asarray(traj.kp), np.asarray(traj.kd))
    lo, hi = _affine_hessian_box(*args, radius, rhat, 0.0, params, *consts)
    centre_h = 0.5 * (lo + hi)[-1]
    spread = 0.0
    for s_hi, weight in zip(seg_hi, weights, strict=True):
        lo, hi = _affine_hessian_box(*args, radius, rhat, s_hi, params, *consts)
        spread = spread + weight * np.maximum(hi[-1] - centre_h, centre_h - lo[-1])
    return spread


def induction_row(
    n,
    splits,
    steps,
    enclosure,
    piece=None,
    duration=1.0,
    segments=3,
    feedback=True,
    propagate="nominal",
    keep=False,
):
    """``certified``'s induction for one piece of the box, replayed in numpy with the
    Hessian spread over the tube enclosed by ``enclosure``: ``"interval"`` (the
    certificate's own 2-jets, to check this replay against it) or ``"affine"`` (the
    prototype backend, :func:`_affine_hessian_box`). A *measurement*: rounding is not
    bounded and the centre model's enclosure widths are left out, so nothing here is
    certified. ``preset_arm(n)``, sine on every joint, each mass range in ``splits``;
    ``piece``: the one whose remainder input is largest at step 1 by default (pieces
    are certified independently, so one piece shows whether its remainder stays
    bounded); ``remainder_over_box_first`` sets the remainder against the first-order
    range the piece's sensitivities give over the whole box, about how much it would
    widen the union of the pieces' bands. ``feedback=False`` leaves out every term of
    the input that involves the remainder ``R`` itself (``gv_R R`` and the Hessian
    blocks with ``R``), keeping the parameter-parameter block: an ablation, to see
    whether the divergence is the remainder's own feedback. Returns per step the largest
    remainder input and its parts (for the joint where it is largest), the largest
    remainder and its ratio to the first-order range; the replay stops once the
    remainder exceeds 10.

    ``propagate``: ``"nominal"`` as ``certified`` does (``R_(k+1) = A R_k + dt e2 w_k``
    with the nominal loop's ``A`` and ``w_k`` including ``|gv_R| |R_k|``, the piece
    centre's first-order feedback of the remainder, in absolute values), or ``"centre"``:
    the remainder propagated through the piece centre's own linearised closed loop
    ``A_c(k) = A + dt e2 gv_R(x_c(k), th_c)`` as a zonotope (the transition matrices
    applied to every past input's generators, so no absolute values are taken around
    the loop), ``w_k`` holding only the second-order terms; or ``"carried"``: the same,
    and the remainder's first-order dependence on the parameters carried too, ``R = R^0
    + sum_b R^b d_b`` with every ``R^b`` a linear image of the same generators
    (``R^b_(k+1) = A_c R^b_k + dt e2 H_b R^0_k``, ``H_b`` the centre's ``d_b``-``R``
    block of the Hessian), so that the parameter-remainder term ``d' H_dR R`` becomes a
    coefficient; ``w_k`` then holds ``1/2 R' H_RR(centre) R``, the second-order ``d_b
    d_c H_b R^c`` and the Lagrange spread of every block about the centre. ``keep``:
    also return the replay's models and bounds per step (for
    :func:`replay_containment`).
    """
    params = rmijax.preset_arm(n)
    traj = rmijax.trajectory(["sine"] * n, duration=duration)
    p, dt = params.n_params, float(traj.dt)
    centers, los, his = _pieces(params, _split_counts(params, splits))
    if piece is None:
        zeros = jnp.zeros((n, 2))
        short = rmijax.trajectory(["sine"] * n, duration=0.03)
        _, _, _, pieces, _, _ = _certify_box(short, params, zeros, zeros, splits)
        piece = int(np.argmax(np.asarray(pieces["injected"])[:, 1].max(axis=(-2, -1))))
    center, radius = centers[piece], 0.5 * (his[piece] - los[piece])
    box_radius = 0.5 * (np.asarray(params.hi) - np.asarray(params.lo))
    kernel, _ = _kernel(traj.kp, traj.kd, traj.dt, steps + 1)
    kernel = np.asarray(kernel)  # (steps, n, 2, 2): |A_i^m|
    kp, kd = np.asarray(traj.kp), np.asarray(traj.kd)
    evaluate = jax.jit(_evaluate)
    seg_hi, weights = _segments(segments)
    d_box = Interval(jnp.asarray(-radius), jnp.asarray(radius))
    xc = np.asarray(traj.x_n[0])
    sens, sens2 = np.zeros((n, 2, p)), np.zeros((n, 2, p, p))
    rhat, injected, rows = np.zeros((n, 2)), [], []
    gens = np.zeros((2 * n, 0))  # propagate="centre": the remainder's zonotope
    carried = np.zeros((p, 2 * n, 0))  # propagate="carried": R^b's generators
    kept = []
    for k in range(steps):
        u = np.asarray(traj.u_d[k])
        consts = dict(nominal=params.nominal, u=u, kp=traj.kp, kd=traj.kd)
        g0, g1, g2 = evaluate(
            Interval(xc), Interval(sens), jnp.asarray(sens2), Interval(center), None, consts
        )
        g0, g1, g2 = (np.asarray(g.mid()) for g in (g0, g1, g2))
        linear = np.abs(g1[:, p:]) * np.reshape(rhat, -1)[None]
        centre_h = np.zeros((n, p + 2 * n, p + 2 * n))
        centre_h[:, :p, :p] = g2[:, :p, :p]
        if propagate == "carried":  # every block's centre value is carried explicitly
            centre_h = np.array(g2)
        spread = 0.0
        for s_hi, weight in zip(seg_hi, weights, strict=True):
            if enclosure == "interval":
                box = d_box * float(s_hi)
                low, high = _poly_range(jnp.asarray(sens), jnp.asarray(sens2), box.lo, box.hi)
                tube = Interval(xc) + Interval(low, high) + Interval(-rhat, rhat) * float(s_hi)
                grad = Interval(sens) + (Interval(sens2) * box[None, None, None, :]).sum(-1)
                _, _, h = evaluate(
                    tube, grad, jnp.asarray(sens2), Interval(center) + box, None, consts
                )
                lo, hi = np.asarray(h.lo), np.asarray(h.hi)
            else:
                lo, hi = _affine_hessian_box(
                    xc, sens, sens2, center, radius, rhat, s_hi, params, u, kp, kd
                )
            spread = spread + weight * np.maximum(hi - centre_h, centre_h - lo)
        v_hat = np.concatenate([radius, np.reshape(rhat, -1)])
        quadratic = spread * v_hat[None, :, None] * v_hat[None, None, :]
        w = quadratic.sum(axis=(-2, -1))
        if propagate == "nominal":
            w = w + linear.sum(-1)
        if propagate == "carried":
            r_flat = np.reshape(rhat, -1)
            # 1/2 R' H_RR(centre) R, and d' H_dR(centre) (sum_c R^c d_c): second order in d
            w = w + 0.5 * np.einsum("iab,a,b->i", np.abs(g2[:, p:, p:]), r_flat, r_flat)
            mixed = g2[:, :p, p:]  # (n, p, 2n): H_b, the centre's d_b-R block
            if carried.shape[-1]:
                through = np.einsum("ibs,csj->ibcj", mixed, carried)  # H_b R^c per generator
                w = w + np.einsum("ibcj,b,c->i", np.abs(through), radius, radius)
        if not feedback:
            w = quadratic[:, :p, :p].sum(axis=(-2, -1))
        worst = int(np.argmax(w))  # the joint whose input is largest: its parts
        parts = dict(
            linear=float(linear[worst].sum()),
            param_param=float(quadratic[worst, :p, :p].sum()),
            param_state=float(2 * quadratic[worst, :p, p:].sum()),
            state_state=float(quadratic[worst, p:, p:].sum()),
        )
        # the next Taylor model (midpoints) and the remainder bound
        q, qd = xc[:, 0], xc[:, 1]
        xc = np.stack([q + dt * qd, qd + dt * (u - kd * qd - kp * q + g0)], axis=1)
        sq, sqd = sens[:, 0], sens[:, 1]
        new_sqd = sqd + dt * (-kd[:, None] * sqd - kp[:, None] * sq + g1[:, :p])
        sens = np.stack([sq + dt * sqd, new_sqd], axis=1)
        qq, qqd = sens2[:, 0], sens2[:, 1]
        gain_d, gain_p = kd[:, None, None], kp[:, None, None]
        new_qqd = qqd + dt * (-gain_d * qqd - gain_p * qq + g2[:, :p, :p])
        sens2 = np.stack([qq + dt * qqd, new_qqd], axis=1)
        sens2 = 0.5 * (sens2 + np.swapaxes(sens2, -1, -2))
        if propagate == "nominal":
            injected.insert(0, np.stack([np.zeros(n), dt * w], axis=1))
            rhat = np.einsum("kiab,kib->ia", kernel[: len(injected)], np.stack(injected))
        else:  # zonotope generators (2n, columns), state order (joint, q/qd)
            a_c = np.zeros((2 * n, 2 * n))
            for i in range(n):
                a_c[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] = [
                    [1.0, dt],
                    [-kp[i] * dt, 1.0 - kd[i] * dt],
                ]
                a_c[2 * i + 1] += dt * g1[i, p:]
            new_gens = np.zeros((2 * n, n))
            new_gens[1::2] = np.diag(dt * w)
            if propagate == "carried":  # R^b += dt e2 H_b R^0, generator by generator
                pushed = np.zeros_like(carried)
                pushed[:, 1::2] = dt * np.einsum("ibs,sj->bij", mixed, gens)
                carried = np.einsum("st,btj->bsj", a_c, carried) + pushed
                carried = np.concatenate([carried, np.zeros((p, 2 * n, n))], axis=-1)
            gens = np.concatenate([a_c @ gens, new_gens], axis=1)
            spread_d = np.einsum("b,bsj->sj", radius, np.abs(carried))
            rhat = (np.sum(np.abs(gens), axis=1) + spread_d.sum(axis=1)).reshape(n, 2)
        first = np.sum(np.abs(sens) * radius, axis=-1)  # (n, 2) first-order range
        box_first = np.sum(np.abs(sens) * box_radius, axis=-1)  # same over the whole box
        if keep:
            kept.append((xc, sens, sens2, rhat))
        rows.append(
            dict(
                step=k + 1,
                w_max=float(w.max()),
                remainder_max=float(rhat.max()),
                remainder_over_first=float(np.max(rhat / np.maximum(first, 1e-300))),
                remainder_over_box_first=float(np.max(rhat / np.maximum(box_first, 1e-300))),
                w_parts=parts,
            )
        )
        if not np.all(np.isfinite(rhat)) or rhat.max() > 10.0:
            break
    return dict(
        links=n,
        splits=splits,
        piece=piece,
        enclosure=enclosure,
        segments=segments,
        feedback=feedback,
        propagate=propagate,
        duration=duration,
        steps=rows,
    ) | (dict(kept=kept, center=center, radius=radius) if keep else {})


def _closed_loop_runs(params, traj, ths, steps):
    """States of the discretised closed loop (SPEC section 3, from ``x_d(0)``) for each
    constant parameter vector in ``ths`` (runs, p): (runs, steps, n, 2), steps 1..steps."""
    kp, kd, dt, nominal = traj.kp, traj.kd, traj.dt, jnp.asarray(params.nominal)

    def run(th):
        def step(x, u):
            q, qd = x[:, 0], x[:, 1]
            gv = coupled_perturbation(params.model, th, nominal, q, qd, u, kp, kd)
            nxt = jnp.stack([q + dt * qd, qd + dt * (u - kd * qd - kp * q + gv)], axis=1)
            return nxt, nxt

        return jax.lax.scan(step, traj.x_n[0], traj.u_d[:steps])[1]

    return np.asarray(jax.jit(jax.vmap(run))(jnp.asarray(ths)))


def replay_containment(row, draws=500, seed=0):
    """Do constant-parameter runs of the replayed piece stay inside its remainder bound?

    ``row``: an :func:`induction_row` made with ``keep=True``. Runs the discretised
    closed loop (SPEC section 3, from ``x_d(0)``) at every corner of the piece (up to
    2^12) and ``draws`` uniform points in it, and compares ``|x_k(th) - x_c(k) - S_k d -
    1/2 Q_k[d, d]|`` with the replay's ``r_k`` at every step. The replay is not a
    certificate (no rounding), so this checks its algebra, not a proof. Returns the
    number of (run, step, output) entries outside and the largest ``|R| / r``.
    """
    n, steps = row["links"], len(row["kept"])
    params = rmijax.preset_arm(n)
    traj = rmijax.trajectory(["sine"] * n, duration=row["duration"])
    p = params.n_params
    center, radius = np.asarray(row["center"]), np.asarray(row["radius"])
    signs = np.array(np.meshgrid(*[[-1.0, 1.0]] * p, indexing="ij")).reshape(p, -1).T
    rng = np.random.default_rng(seed)
    ds = np.concatenate([signs[: 2**12], rng.uniform(-1, 1, (draws, p))]) * radius
    xs = _closed_loop_runs(params, traj, center + ds, steps)  # (runs, steps, n, 2)
    outside, largest = 0, 0.0
    for k, (xc, sens, sens2, rhat) in enumerate(row["kept"]):
        poly = xc + np.einsum("isb,rb->ris", sens, ds)
        poly = poly + 0.5 * np.einsum("isab,ra,rb->ris", sens2, ds, ds)
        error = np.abs(xs[:, k] - poly)
        outside += int(np.sum(error > rhat + 1e-12))
        largest = max(largest, float(np.max(error / np.maximum(rhat, 1e-300))))
    return dict(runs=int(ds.shape[0]), steps=steps, outside=outside, largest_ratio=largest)


def union_row(n, splits, steps, draws=1000, seed=0):
    """The band the 'carried' affine replay would give: every piece of the box replayed
    (:func:`induction_row`), each piece's ``x_c + range(S d + 1/2 Q[d, d]) +- r_k`` and
    their union, against the range of constant-parameter runs of the closed loop over the
    whole box (every corner up to 2^12 and ``draws`` uniform points). Not a certificate
    (no rounding); it says how tight such a certificate could be. ``preset_arm(n)``,
    sine on every joint, the first ``steps`` steps.
    """
    params = rmijax.preset_arm(n)
    duration = steps / 100 + 0.01
    traj = rmijax.trajectory(["sine"] * n, duration=duration)
    centers, _, _ = _pieces(params, _split_counts(params, splits))
    lower = np.full((steps, n, 2), np.inf)
    upper = np.full((steps, n, 2), -np.inf)
    diverged = []
    for piece in range(centers.shape[0]):
        row = induction_row(
            n,
            splits,
            steps,
            "affine",
            piece=piece,
            duration=duration,
            propagate="carried",
            keep=True,
        )
        if len(row["kept"]) < steps:
            diverged.append(piece)
            continue
        radius = row["radius"]
        for k, (xc, sens, sens2, rhat) in enumerate(row["kept"]):
            low, high = _poly_range(jnp.asarray(sens), jnp.asarray(sens2), -radius, radius)
            lower[k] = np.minimum(lower[k], xc + np.asarray(low) - rhat)
            upper[k] = np.maximum(upper[k], xc + np.asarray(high) + rhat)
    p = params.n_params
    lo, hi = np.asarray(params.lo), np.asarray(params.hi)
    signs = np.array(np.meshgrid(*[[0.0, 1.0]] * p, indexing="ij")).reshape(p, -1).T
    rng = np.random.default_rng(seed)
    ths = lo + np.concatenate([signs[: 2**12], rng.uniform(0, 1, (draws, p))]) * (hi - lo)
    xs = _closed_loop_runs(params, traj, ths, steps)  # (runs, steps, n, 2)
    seen_lo, seen_hi = xs.min(axis=0), xs.max(axis=0)
    outside = int(np.sum((xs < lower - 1e-12) | (xs > upper + 1e-12))) if not diverged else -1
    seen = seen_hi - seen_lo  # outputs the parameters do not move yet (step 1's q) skipped
    ratio = np.where(seen > 1e-12, (upper - lower) / np.maximum(seen, 1e-300), np.nan)
    late = ratio[50:] if steps > 50 else ratio
    return dict(
        links=n,
        splits=splits,
        pieces=int(centers.shape[0]),
        steps=steps,
        diverged_pieces=diverged,
        runs=int(ths.shape[0]),
        runs_outside=outside,
        width_over_seen_median=[float(np.nanmedian(late[..., s])) for s in range(2)],
        width_over_seen_p90=[float(np.nanpercentile(late[..., s], 90)) for s in range(2)],
        width_over_seen_min=[float(np.nanmin(late[..., s])) for s in range(2)],
    )


def _one_chain_piece(traj, params, diagnostics=False):
    """``certified``'s run of the whole box as one piece with its chain defaults
    (affine/carried, preconditioned solve): the piece's arrays (numpy, no piece axis)
    and the seconds to its end, compile included."""
    zeros = jnp.zeros((traj.n_joints, 2))
    options = dict(enclosure="affine", propagate="carried", solve="preconditioned")
    started = time.perf_counter()
    out = _certify_box(traj, params, zeros, zeros, 1, diagnostics=diagnostics, **options)
    out = jax.block_until_ready(out)
    seconds = time.perf_counter() - started
    return {key: np.asarray(value)[0] for key, value in out[3].items()}, seconds


ARM_CASES = ("ur5e_box", "panda_box", "iiwa14_box")
"""``--arms``: the shipped arms under their whole default box (``benchmarks/certified.py``'s
cases of those names: the first steps of ``rmijax --robot``'s move)."""


def arm_remainder_row(case, duration=0.1, draws=400, corners=400, seed=0):
    """On a loaded arm: ``certified``'s remainder radius (one piece, its defaults:
    affine/carried, preconditioned solve; until it stops being finite) against the
    *true* remainder of the same Taylor model, ``max |x_k(th) - (x_c + S_k d + 1/2
    Q_k[d, d])|`` over ``draws`` uniform points and ``corners`` random corners of the box
    (runs of :func:`rmijax.simulate`; a lower bound of what the radius must cover), per
    step and sensor (largest joint). Where the radius is far above the truth the
    enclosure of ``gv``'s Hessian over the tube is what fails, not the second-order
    model. Also ``w_k`` (rad/s^2, largest joint) and, per step, the blocks of its
    quadratic part: the mass scales (m, "mm"), the other parameters (payload, friction:
    "l") and the remainder (x)."""
    from certified import CASES  # benchmarks/certified.py: the same cases

    build, motion = CASES[case]
    params, traj = build(), motion(duration)
    piece, seconds = _one_chain_piece(traj, params, diagnostics=True)
    lo, hi = np.asarray(params.lo), np.asarray(params.hi)
    rng = np.random.default_rng(seed)
    bits = rng.integers(0, 2, size=(corners, lo.size)).astype(bool)
    ths = np.concatenate(
        [lo + (hi - lo) * rng.uniform(size=(draws, lo.size)), np.where(bits, hi, lo)]
    )
    states = np.asarray(rmijax.simulate(traj, params, ths)[0])  # (runs, T+1, n, 2)
    d = ths - np.asarray(params.nominal)
    model = (
        piece["state"][None]
        + np.einsum("tijb,sb->stij", piece["sens"], d)
        + 0.5 * np.einsum("tijbc,sb,sc->stij", piece["sens2"], d, d)
    )
    true = np.abs(states - model).max(axis=(0, 2))  # (T+1, 2)
    radius = piece["remainder"].max(axis=1)  # (T+1, 2)
    spread = (states.max(axis=0) - states.min(axis=0)).max(axis=1)
    blocks = piece["w_blocks"]  # (T, n, 10)
    steps = []
    for k in range(1, traj.n_steps + 1):
        if not np.all(np.isfinite(piece["remainder"][k])):
            break
        joint = int(np.argmax(blocks[k - 1, :, 1:].sum(axis=-1)))
        steps.append(
            dict(
                step=k,
                radius=[float(v) for v in radius[k]],
                true=[float(v) for v in true[k]],
                spread=[float(v) for v in spread[k]],
                w=float(blocks[k - 1, joint].sum()),
                w_joint=joint,
                w_blocks={b: float(v) for b, v in zip(BLOCKS, blocks[k - 1, joint], strict=True)},
            )
        )
    return dict(
        case=case,
        duration=duration,
        runs=int(ths.shape[0]),
        finite_steps=len(steps),
        seconds=round(seconds, 1),
        steps=steps,
    )


BOX_PARTS = {
    "whole": ("mass", "payload", "viscous", "coulomb"),
    "no_coulomb": ("mass", "payload", "viscous"),
    "masses_payload": ("mass", "payload"),
    "masses_payload_coulomb": ("mass", "payload", "coulomb"),
}
"""``--parts``: which ranges of the default box are uncertain (the others at nominal)."""


def box_part_row(name, part, duration=1.0):
    """``certified_bounds`` (one piece, its defaults) on arm ``name``'s move under part
    ``part`` of :func:`rmijax.robots.loaders.default_box` (:data:`BOX_PARTS`): the first
    step whose band is not finite (None: finite over ``duration`` s), the largest
    remainder radius over the finite steps against the band's half-width there
    (tachometers; near 1 when it diverges), and the seconds it took (compile
    included)."""
    from certified import CASES

    from rmijax.robots.loaders import default_box

    box, kinds = default_box(name), BOX_PARTS[part]
    options = {key: box[key] for key in ("mass", "payload") if key in kinds}
    friction = {kind: box["friction"][kind] for kind in ("viscous", "coulomb") if kind in kinds}
    if friction:
        options["friction"] = friction
    params = rmijax.load_robot(name, **options)
    traj = CASES[f"{name}_box"][1](duration)
    piece, seconds = _one_chain_piece(traj, params)
    finite = np.all(np.isfinite(piece["upper"] - piece["lower"]), axis=(1, 2))
    first = None if finite.all() else int(np.argmin(finite))
    upto = piece["remainder"][: first if first is not None else None][..., 1]
    half = 0.5 * (piece["upper"] - piece["lower"])[: upto.shape[0]][..., 1]
    return dict(
        arm=name,
        part=part,
        uncertain=list(kinds),
        duration=duration,
        steps=traj.n_steps,
        first_non_finite_step=first,
        remainder_over_half_width_max=float(np.max(upto / np.maximum(half, 1e-300))),
        seconds=round(seconds, 1),
    )


def _certificate_remainder(row, steps):
    """The largest relative difference between an interval replay's remainder and the
    certificate's own, for the same piece over the same steps (1 s sine)."""
    n = row["links"]
    params = rmijax.preset_arm(n)
    traj = rmijax.trajectory(["sine"] * n, duration=1.0)
    zeros = jnp.zeros((n, 2))
    _, _, _, pieces, _, _ = _certify_box(traj, params, zeros, zeros, row["splits"])
    own = np.asarray(pieces["remainder"])[row["piece"]]
    replay = np.array([r["remainder_max"] for r in row["steps"]])
    reference = np.array([own[k].max() for k in range(1, len(replay) + 1)])
    return dict(steps=steps, max_rel_difference=float(np.max(np.abs(replay / reference - 1))))


TUBE_VARIANTS = {
    "point_state_no_chain": ("point", "zero"),
    "box_state_no_chain": ("box", "zero"),
    "point_state_centre_chain": ("point", "centre"),
    "point_state_full_chain": ("point", "full"),
    "box_state_centre_chain": ("box", "centre"),
    "box_state_full_chain": ("box", "full"),
}
"""How the interval Hessian of ``gv`` at a tube step is evaluated in ``_tube_attribution``:
the state's *value* as the tube's box or its centre point, and its derivatives in ``d``
(the chain rule's ``S`` and ``Q``) left out (``zero``), at the centre (``S``, ``Q``) or
as over the box (``S + Q d``, ``Q``; what ``certified`` does)."""


def _tube_attribution(pieces, piece, k, centers, los, his, params, traj):
    """The parameter-parameter quadratic of the Hessian spread at step ``k`` (last joint,
    whole box, one segment: ``1/2 sum_ab |H_ab - H_ab(centre)| r_a r_b``, rad/s^2)
    under each evaluation of :data:`TUBE_VARIANTS`: which part of the tube widens the
    interval enclosure. Only the last variant is a sound enclosure over the tube; the
    others leave part of it out, so they measure, not bound."""
    p = params.n_params
    consts = dict(nominal=params.nominal, u=traj.u_d[k], kp=traj.kp, kd=traj.kd)
    centre = jnp.asarray(centers[piece])
    d_box = Interval(jnp.asarray(los[piece]) - centre, jnp.asarray(his[piece]) - centre)
    radius = 0.5 * (np.asarray(his[piece]) - np.asarray(los[piece]))
    xc, sens, sens2, rhat = (
        pieces[key][piece, k] for key in ("state", "sens", "sens2", "remainder")
    )
    _, _, centre_h = _evaluate(Interval(xc), Interval(sens), sens2, Interval(centre), None, consts)
    low, high = _poly_range(sens, sens2, d_box.lo, d_box.hi)
    tube = Interval(xc) + Interval(low, high) + Interval(-rhat, rhat)
    out = {}
    for name, (value, chain) in TUBE_VARIANTS.items():
        state = tube if value == "box" else Interval(xc)
        grad = {
            "zero": Interval(jnp.zeros_like(sens)),
            "centre": Interval(sens),
            "full": Interval(sens) + (Interval(sens2) * d_box[None, None, None, :]).sum(-1),
        }[chain]
        second = jnp.zeros_like(sens2) if chain == "zero" else sens2
        _, _, h_box = _evaluate(state, grad, second, Interval(centre) + d_box, None, consts)
        mid = centre_h.mid()
        spread = np.asarray(jnp.maximum(h_box.hi - mid, mid - h_box.lo))[-1, :p, :p]
        out[name] = float(0.5 * np.sum(spread * np.outer(radius, radius)))
    return out


ENCLOSURE_COLUMNS = [
    ("links", "n", "{:>2d}"),
    ("box_fraction", "box", "{:>5.2f}"),
    ("first", "first (max)", "{:>11.3g}"),
    ("true", "true (max)", "{:>10.3g}"),
    ("interval", "interval (max)", "{:>14.3g}"),
    ("affine", "affine (max)", "{:>12.3g}"),
    ("interval_over_true_max", "interval/true", "{:>13.1f}"),
    ("affine_over_true_max", "affine/true", "{:>11.1f}"),
]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--links", type=int, nargs="+", default=[2, 4, 6])
    parser.add_argument("--fractions", type=float, nargs="+", default=[1.0, 0.5, 0.25])
    parser.add_argument(
        "--scale-runs",
        nargs="+",
        default=["1:1", "1:0.1", "1:0.01", "1:0.001", "2:1", "2:0.1", "2:0.01"],
        help="splits:remainder_scale runs of preset_arm(4)",
    )
    parser.add_argument("--duration", type=float, default=1.0, help="s, the scale runs and --parts")
    parser.add_argument(
        "--neumann",
        action="store_true",
        help="only the Hessian-free remainder bounds (neumann_row, real_arm_row), minutes",
    )
    parser.add_argument(
        "--robots",
        nargs="*",
        default=["panda", "iiwa14", "ur5e"],
        help="--neumann: shipped arms under their default box, besides preset_arm(--links)",
    )
    parser.add_argument(
        "--blocks",
        action="store_true",
        help="only where certified's remainder input comes from (blocks_row), minutes",
    )
    parser.add_argument(
        "--tube",
        action="store_true",
        help="only the remainder input's quadratic part against the sampled Hessian over "
        "the same tube (tube_row), minutes",
    )
    parser.add_argument(
        "--induction",
        action="store_true",
        help="only certified's induction replayed for one piece with the affine enclosure "
        "(induction_row), minutes",
    )
    parser.add_argument(
        "--union",
        action="store_true",
        help="only the band every piece's 'carried' affine replay would give, against "
        "sampled runs (union_row), about 15 minutes",
    )
    parser.add_argument(
        "--union-steps", type=int, default=100, help="--union: steps replayed (100 = 1 s)"
    )
    parser.add_argument(
        "--arms",
        action="store_true",
        help="only the remainder radius against the true remainder on the shipped arms' "
        "default box (arm_remainder_row), minutes",
    )
    parser.add_argument(
        "--parts",
        action="store_true",
        help="only which part of the shipped arms' default box makes certified diverge "
        "(box_part_row), about 15 minutes",
    )
    parser.add_argument("--json", default=None, help="write results here")
    args = parser.parse_args(argv)
    meta = run_meta("benchmarks/certified_enclosure.py", argv, dtype="float64")
    if args.blocks:
        rows = [blocks_row(2, 4, 0.3), blocks_row(4, 2, 0.3)]
        for row in rows:
            print(f"preset_arm({row['links']}), splits {row['splits']}: share of w_k by block")
            print("step  w_k (rad/s^2, last joint)  " + "  ".join(f"{b:>6}" for b in BLOCKS))
            for r in row["steps"]:
                shares = "  ".join(f"{r[b]:6.3f}" for b in BLOCKS)
                print(f"{r['step']:>4}  {r['w']:>10.3g}  {shares}")
        if args.json:
            write_json(args.json, dict(blocks=rows), meta)
        return
    if args.parts:
        rows = []
        for name in args.robots:
            for part in BOX_PARTS:
                rows.append(box_part_row(name, part, args.duration))
                r = rows[-1]
                print(
                    f"{name:7} {part:24} first non-finite step {r['first_non_finite_step']} "
                    f"of {r['steps']}, remainder / half-width (tachometers) up to "
                    f"{r['remainder_over_half_width_max']:.3g}, {r['seconds']} s",
                    flush=True,
                )
        if args.json:
            write_json(args.json, dict(parts=rows), meta)
        return
    if args.arms:
        rows = [arm_remainder_row(case) for case in ARM_CASES]
        for row in rows:
            print(f"{row['case']}: {row['finite_steps']} finite steps, {row['seconds']} s")
            print("step  radius qd  true qd  radius/true qd  spread qd  w_k (rad/s^2)")
            for r in row["steps"]:
                print(
                    f"{r['step']:>4}  {r['radius'][1]:9.3g}  {r['true'][1]:7.3g}  "
                    f"{r['radius'][1] / r['true'][1]:14.1f}  {r['spread'][1]:9.3g}  {r['w']:.3g}"
                )
        if args.json:
            write_json(args.json, dict(arms=rows), meta)
        return
    if args.tube:
        rows = [tube_row(2, 4, (0, 1, 2, 3, 9)), tube_row(4, 2, (0, 1, 2, 3))]
        for row in rows:
            print(f"preset_arm({row['links']}), splits {row['splits']}: quadratic part of w_k")
            print("step  r_k max   interval   affine   sampled  interval/sampled per block")
            for r in row["steps"]:
                ratios = "  ".join(
                    f"{b} {r['interval'][b] / r['sampled'][b]:.0f}"
                    for b in BLOCKS[1:]
                    if r["sampled"][b] > 0
                )
                print(
                    f"{r['step']:>4}  {r['remainder_max']:.3g}  {r['interval_total']:.3g}  "
                    f"{r['affine_total']:.3g}  {r['sampled_total']:.3g}  {ratios}"
                )
                shown = ", ".join(f"{key} {value:.3g}" for key, value in r["attribution"].items())
                print(f"      parameter block, one segment: {shown}")
        if args.json:
            write_json(args.json, dict(tube=rows), meta)
        return
    if args.union:
        rows = [union_row(2, 4, args.union_steps), union_row(4, 3, args.union_steps)]
        for row in rows:
            print(
                f"preset_arm({row['links']}), {row['pieces']} pieces, {row['steps']} steps: "
                f"diverged pieces {row['diverged_pieces']}, runs outside "
                f"{row['runs_outside']} of {row['runs']}; width / sampled range after 0.5 s, "
                f"encoder and tachometer: median {np.round(row['width_over_seen_median'], 3)}"
                f", p90 {np.round(row['width_over_seen_p90'], 3)}, min "
                f"{np.round(row['width_over_seen_min'], 3)}",
                flush=True,
            )
        if args.json:
            write_json(args.json, dict(union=rows), meta)
        return
    if args.induction:
        runs = [
            dict(n=2, splits=4, steps=30, enclosure="interval"),
            dict(n=2, splits=4, steps=100, enclosure="affine"),
            dict(n=2, splits=4, steps=100, enclosure="affine", propagate="centre"),
            dict(n=4, splits=2, steps=100, enclosure="interval"),
            dict(n=4, splits=2, steps=100, enclosure="interval", feedback=False),
            dict(n=4, splits=2, steps=100, enclosure="affine", feedback=False),
        ]
        for splits in (2, 3, 4):
            for propagate in ("nominal", "centre", "carried"):
                runs.append(
                    dict(n=4, splits=splits, steps=100, enclosure="affine", propagate=propagate)
                )
        long = dict(steps=300, duration=3.0, enclosure="affine", propagate="carried", keep=True)
        runs += [dict(n=2, splits=4, **long), dict(n=4, splits=3, **long)]
        runs += [dict(n=4, splits=4, **long)]
        rows = []
        for run in runs:
            row = induction_row(**run)
            if run.get("keep"):
                row["containment"] = replay_containment(row)
                print(f"  sampled runs against the replay's bound: {row['containment']}")
                row.pop("kept")
                row["center"], row["radius"] = row["center"].tolist(), row["radius"].tolist()
            steps = row["steps"]
            bounded = steps[-1]["remainder_max"] <= 10.0 and len(steps) == run["steps"]
            row["bounded"] = bool(bounded)
            if row["enclosure"] == "interval" and row["links"] == 2:
                row["certificate_remainder"] = _certificate_remainder(row, run["steps"])
            rows.append(row)
            parts = steps[min(10, len(steps)) - 1]["w_parts"]
            print(
                f"preset_arm({row['links']}) splits {row['splits']} piece {row['piece']} "
                f"{row['enclosure']} propagate={row['propagate']} feedback={row['feedback']}: "
                + (
                    f"bounded over {len(steps)} steps"
                    if bounded
                    else f"remainder above 10 at step {steps[-1]['step']}"
                )
                + f"; r/first-order max {max(r['remainder_over_first'] for r in steps):.3g}; "
                f"w at step 1 {steps[0]['w_max']:.3g}; parts at step {min(10, len(steps))}: "
                + ", ".join(f"{key} {value:.3g}" for key, value in parts.items()),
                flush=True,
            )
        if args.json:
            write_json(args.json, dict(induction=rows), meta)
        return
    if args.neumann:
        rows = [neumann_row(n) for n in args.links]
        rows += [real_arm_row(name) for name in args.robots]
        for row in rows:
            print(
                f"{row.get('robot', 'preset_arm')} n={row['links']}: row-sum norm "
                f"{np.round(row['row_sum_norm'], 3).tolist()}, "
                f"Perron root {np.round(row['perron_root'], 3).tolist()}"
            )
            for i in range(row["states"]):
                sampled = np.asarray(row["sampled"][i])
                ratio = {
                    key: np.round(np.asarray(row[key][i]) / sampled, 1).tolist()
                    for key in ("bound_joint", "bound_energy", "bound_min")
                }
                print(
                    f"  state {i}: sampled remainder (max joint) {sampled.max():.3g} rad/s^2, "
                    f"first order {max(row['first_order'][i]):.3g}; bound / sampled per "
                    f"joint: joint coordinates {ratio['bound_joint']}, energy norm "
                    f"{ratio['bound_energy']}, min {ratio['bound_min']} (rho "
                    f"{row['energy_rho'][i]:.3f})"
                )
        if args.json:
            write_json(args.json, dict(neumann=rows), meta)
        return
    rows = []
    for n in args.links:
        for fraction in args.fractions:
            rows.append(enclosure_row(n, fraction))
            print(f"n={n} box x{fraction}: done", flush=True)
    shown = [{k: (max(v) if isinstance(v, list) else v) for k, v in row.items()} for row in rows]
    print(table(shown, ENCLOSURE_COLUMNS))
    scales = []
    for run in args.scale_runs:
        splits, scale = run.split(":")
        scales.append(scale_row(int(splits), float(scale), args.duration))
    for row in scales:
        print(row, flush=True)
    if args.json:
        write_json(args.json, dict(enclosure=rows, remainder_scale=scales), meta)


if __name__ == "__main__":
    main()
