"""Certified bounds on the loaded serial chains (UR5e, Panda, iiwa14): the perturbation's
jets against the model, ``tanh`` in every backend, soundness and teeth on a small box, and
the independent checker on a chain certificate."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rmijax
from rmijax import _affine, _intervals as intervals
from rmijax._intervals import Interval, Jet
from rmijax.apps.real_arm import real_arm_case
from rmijax.methods import certified
from rmijax.methods.certificate_check import _iv, _tanh, check_certificate
from rmijax.methods.chain_jets import chain_perturbation_jets
from rmijax.robots.loaders import default_box

from helpers import jets_at_a_point

ARMS = ("ur5e", "panda", "iiwa14")
TOL = 1e-12


def _box(name, share):
    """``share`` of the default box: mass scales, payload and friction ranges."""
    box = default_box(name)
    return dict(
        mass=box["mass"] * share,
        payload=(0.0, box["payload"][1] * share),
        friction={kind: pairs * share for kind, pairs in box["friction"].items()},
    )


def _model_gv(params, q, qd, u, kp, kd, th, eta=None):
    """``gv = qdd - v`` from the float64 model: the plant at ``th`` under the nominal
    computed torque on the readings ``x + eta``."""
    model, nominal = params.model, params.nominal
    v = u - kd * qd - kp * q
    yq, yqd = (q, qd) if eta is None else (q + eta[:, 0], qd + eta[:, 1])
    vy = u - kd * yqd - kp * yq
    tau = model.torques(yq, yqd, vy, nominal)
    return model.accelerations(q, qd, tau, th) - v


def _point(params, seed):
    n = params.n_joints
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(params.lo), np.asarray(params.hi)
    th = lo + (hi - lo) * rng.uniform(size=lo.size)
    return th, rng.normal(size=n), rng.normal(size=n) * 0.3, rng.normal(size=n) * 3.0


@pytest.mark.parametrize("name", ARMS)
def test_chain_jets_equal_the_model_at_a_point(name):
    """The jets' value (body-frame Newton-Euler, composite inertias, and the tip-first
    ``U D U'`` solve or the preconditioned elimination, in the checker's mpmath
    intervals) equals ``gv`` of the float64 model (:func:`rmijax.load_robot`'s
    Featherstone recursions in the base frame) at a random state, parameter and
    feed-forward, noise through the controller included. The preconditioned solve gives
    the same value for any invertible ``P``: ``M^-1`` at the point, the identity, that
    inverse with every entry moved up to 20 %."""
    params = rmijax.load_robot(name, **_box(name, 1.0))
    layout = params.model.structure.layout
    n = params.n_joints
    th, q, qd, u = _point(params, 1)
    kp, kd = np.full(n, 100.0), np.full(n, 20.0)
    eta = np.random.default_rng(2).uniform(-0.01, 0.01, size=(n, 2))
    inverse = np.linalg.inv(np.asarray(params.model.mass_matrix(q, th)))
    perturbed = inverse * np.random.default_rng(3).uniform(0.8, 1.2, size=(n, n))
    solves = [None, inverse, np.eye(n), perturbed]
    function = functools.partial(chain_perturbation_jets, layout)
    arrays = (q, qd, th, np.asarray(params.nominal), u, kp, kd)
    for noise, precond in [(noise, p) for noise in (None, eta) for p in solves]:
        lower, upper = jets_at_a_point(function, arrays, noise, precond)
        expected = np.asarray(_model_gv(params, q, qd, u, kp, kd, th, noise))
        assert np.all(upper - lower < 1e-9)
        np.testing.assert_allclose(0.5 * (lower + upper), expected, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("name", ARMS)
def test_chain_jets_derivatives_equal_autodiff(name):
    """The tape's gradient and Hessian in ``(d, R)`` at a point (JAX interval jets, as the
    certifier evaluates them) enclose the float64 model's, taken by forward-mode
    autodiff."""
    params = rmijax.load_robot(name, **_box(name, 1.0))
    n, p = params.n_joints, params.n_params
    th, q, qd, u = _point(params, 3)
    kp, kd = np.full(n, 100.0), np.full(n, 20.0)
    x = np.stack([q, qd], axis=1)
    consts = dict(nominal=params.nominal, u=jnp.asarray(u), kp=jnp.asarray(kp), kd=jnp.asarray(kd))
    consts["precond"] = certified._preconditioner(
        params.model.mass_matrix, jnp.asarray(x), jnp.asarray(th), None, None
    )
    value, grad, hess = certified._evaluate(
        Interval(jnp.asarray(x)),
        Interval(jnp.zeros((n, 2, p))),
        jnp.zeros((n, 2, p, p)),
        Interval(jnp.asarray(th)),
        None,
        consts,
        certified._layout(params),
    )

    def gv(z):  # z = (d, x row-major): the variables of the jets
        state = z[p:].reshape(n, 2)
        return _model_gv(params, state[:, 0], state[:, 1], u, kp, kd, th + z[:p])

    def jacobian(z):  # forward over forward, one pass for both (a third of jax.hessian's time)
        jac = jax.jacfwd(gv)(z)
        return jac, jac

    z0 = jnp.concatenate([jnp.zeros(p), jnp.asarray(x).reshape(-1)])
    hessian, jac = jax.jacfwd(jacobian, has_aux=True)(z0)
    expected = (gv(z0), jac, hessian)
    for got, want in zip((value, grad, hess), expected, strict=True):
        # the enclosure holds autodiff's value (up to autodiff's own rounding) and is
        # narrow: the preconditioned solve's products ``P M`` cancel terms of size
        # ``|P| |M|``, so its point enclosures are ~cond(M) eps wide, not eps
        want, size = np.asarray(want), 1.0 + np.max(np.abs(np.asarray(want)))
        assert np.all(np.asarray(got.hi - got.lo) < 1e-6 * size)
        assert np.all(np.asarray(got.lo) <= want + 1e-11 * size)
        assert np.all(np.asarray(got.hi) >= want - 1e-11 * size)


def test_tanh_encloses_in_every_backend():
    """``tanh`` over intervals (JAX and mpmath), its jets' derivatives over an interval,
    and the affine forms (JAX and the checker's) contain the exact values (mpmath at 60
    digits) at points drawn inside."""
    import mpmath

    mpmath.mp.dps = 60
    rng = np.random.default_rng(0)
    centers = np.concatenate([rng.normal(size=40) * 3, [0.0, 1e-8, -30.0, 25.0]])
    radii = np.concatenate([rng.uniform(0, 1, size=40), [0.5, 1e-9, 2.0, 0.0]])
    box = Interval(jnp.asarray(centers - radii), jnp.asarray(centers + radii))
    enclosed = intervals.tanh(box)

    def bend(k):  # one jet per row: the value over [c - r, c + r], unit gradient
        one = Interval(jnp.ones(1))
        jet = Jet(box[k], one, Interval(jnp.zeros((1, 1))), intervals.JAX_BACKEND)
        return jet.tanh()

    form = _affine.AffineForm(
        jnp.asarray(centers), jnp.asarray(radii)[:, None], jnp.zeros(centers.size)
    )
    linear = _affine.tanh(form)
    low, high = (np.asarray(b) for b in linear.bounds())
    iv = _iv()
    for k, (c, r) in enumerate(zip(centers, radii, strict=True)):
        checked = _tanh(iv, iv.mpf([c - r, c + r]))
        bent = bend(k)
        for t in np.linspace(-1.0, 1.0, 11):
            x = mpmath.mpf(float(c)) + mpmath.mpf(float(r)) * mpmath.mpf(float(t))
            value = mpmath.tanh(x)
            slope = 1 - value**2
            curve = -2 * value * slope
            assert float(enclosed.lo[k]) <= value <= float(enclosed.hi[k])
            assert float(bent.g.lo[0]) <= slope <= float(bent.g.hi[0])
            assert float(bent.h.lo[0, 0]) <= curve <= float(bent.h.hi[0, 0])
            assert checked.a <= value <= checked.b
            # the affine form at eps = t: c + r t + [-e, e]
            mid = float(linear.c[k]) + float(linear.a[k, 0]) * float(t)
            assert abs(value - mpmath.mpf(mid)) <= float(linear.e[k]) * (1 + 1e-12) + 1e-300
            assert float(low[k]) <= value <= float(high[k])


def _short(traj, steps):
    keys = ("t", "q_d", "qd_d", "qdd_d", "u_d", "x_n", "qdd_n")
    return dataclasses.replace(traj, **{k: getattr(traj, k)[: steps + 1] for k in keys})


@pytest.fixture(scope="module")
def ur5e_small():
    """The UR5e on a tenth of its default box (masses +-1 %, payload 0-0.1 kg, a tenth of
    the friction ranges), the first 0.3 s of the pick-and-place move: the band and 458
    sampled runs (``_samples``)."""
    case = real_arm_case("ur5e", box=_box("ur5e", 0.1))
    traj = _short(case.traj, 30)
    bounds, cert = certified.certified_bounds(traj, case.params)
    states = np.asarray(rmijax.simulate(traj, case.params, _samples(case.params))[0])
    return traj, case.params, bounds, states


def _samples(params, seed=0, draws=200, corners=256):
    """Uniform draws and random corners of the box (``2^19`` corners: a sample of them)."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(params.lo), np.asarray(params.hi)
    inside = lo + (hi - lo) * rng.uniform(size=(draws, lo.size))
    bits = rng.integers(0, 2, size=(corners, lo.size)).astype(bool)
    return np.concatenate([inside, np.where(bits, hi, lo), [lo, hi]])


def _escape(bounds, states):
    return float(
        max(
            np.max(states - np.asarray(bounds.upper)),
            np.max(np.asarray(bounds.lower) - states),
        )
    )


def test_chain_band_contains_samples_and_is_tight(ur5e_small):
    """Zero of 458 constant-parameter runs (200 uniform draws, 256 random corners, both
    box ends) leave the band, and at the last step it is within 2x of their spread
    (measured 1.04-1.64 with 1.02-1.32 at the 0.3 s end)."""
    traj, params, bounds, states = ur5e_small
    assert _escape(bounds, states) <= TOL
    width = np.asarray(bounds.upper - bounds.lower)
    spread = states.max(0) - states.min(0)
    assert np.all(width[-1] <= 2.0 * spread[-1])


def test_chain_remainder_switched_off_lets_samples_escape(ur5e_small):
    """Teeth: without the remainder (the Taylor polynomial alone) sampled runs leave the
    band, so the containment above rests on it."""
    traj, params, _, states = ur5e_small
    bounds, _ = certified.certified_bounds(traj, params, remainder_scale=0.0)
    assert _escape(bounds, states) > 1e-9


@pytest.mark.slow
@pytest.mark.parametrize(
    ("enclosure", "propagate", "steps"), [("interval", "kernel", 2), ("affine", "carried", 1)]
)
def test_checker_verifies_a_chain_certificate(enclosure, propagate, steps):
    """The independent checker (mpmath jets of the chain: 4 s a step with interval jets,
    24-96 s with affine ones, by host) re-verifies the first steps of a UR5e certificate
    and rejects a centre that moves a certain parameter; with interval jets it also rejects
    the halved-remainder mutant (with affine jets that rejection costs a second full check,
    96 s on a 2-core AMD host; the affine checker's rejection of a halved remainder is
    tested on the two-joint URDF, ``test_checker_verifies_a_coulomb_range_certificate``).
    The payload alone is uncertain: the six mass scales (``lo == hi``) are constants of
    the jets for both the certifier and the checker (``m = 13`` variables, not 19; the
    checker's cost grows with the cube of it)."""
    params = rmijax.load_robot("ur5e", payload=(0.0, 0.2))
    traj = _short(real_arm_case("ur5e").traj, steps + 1)
    options = dict(enclosure=enclosure, propagate=propagate)
    _, cert = certified.certified_bounds(traj, params, **options)
    result = check_certificate(cert, traj, params, steps=steps)
    assert result.ok, result.reason
    if enclosure == "interval":
        _, mutant = certified.certified_bounds(traj, params, remainder_scale=0.5, **options)
        rejected = check_certificate(mutant, traj, params, steps=steps)
        assert not rejected.ok
        assert "below the recomputed bound" in rejected.reason
    # the certain mass scales are constants of the jets only at their value
    moved = dataclasses.replace(cert, center=cert.center.at[0, 0].add(1e-9))
    rejected = check_certificate(moved, traj, params, steps=steps)
    assert not rejected.ok
    assert "centre lies outside the piece" in rejected.reason


def test_affine_hessian_over_the_panda_mass_and_payload_box():
    """Over the default box's masses and payload together (the Panda, 8 parameters) the
    affine Hessian of ``gv`` in ``(d, R)`` is finite and holds autodiff's Hessian of the
    float64 model at 200 points of the box (half of them corners). Before the solve was
    preconditioned an articulated inertia's enclosure held 0 here: every entry NaN."""
    box = default_box("panda")
    params = rmijax.load_robot("panda", mass=box["mass"], payload=box["payload"])
    layout = certified._layout(params)
    n, p = params.n_joints, params.n_params
    th, q, qd, u = _point(params, 4)
    center = jnp.asarray(params.nominal)
    d_rad = 0.5 * (jnp.asarray(params.hi) - jnp.asarray(params.lo))
    kp, kd = np.full(n, 100.0), np.full(n, 20.0)
    xc = jnp.asarray(np.stack([q, qd], axis=1))
    rhat = jnp.full((n, 2), 1e-3)
    consts = dict(nominal=center, u=jnp.asarray(u), kp=jnp.asarray(kp), kd=jnp.asarray(kd))
    consts["precond"] = certified._preconditioner(params.model.mass_matrix, xc, center, None, None)
    zeros = jnp.zeros((n, 2, p))
    lo, hi = certified._evaluate_affine(
        xc, zeros, jnp.zeros((n, 2, p, p)), center, d_rad, rhat, None, 1.0, consts, layout
    )
    lo, hi = np.asarray(lo), np.asarray(hi)
    assert np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))

    def gv(z):
        state = xc + z[p:].reshape(n, 2)
        return _model_gv(params, state[:, 0], state[:, 1], u, kp, kd, center + z[:p])

    scales = np.concatenate([np.asarray(d_rad), np.asarray(rhat).reshape(-1)])
    points = np.random.default_rng(5).uniform(-1, 1, (200, scales.size))
    points[::2] = np.sign(points[::2])
    hessian = jax.jacfwd(jax.jacfwd(gv))  # half of jax.hessian's (reverse inside) compile
    hessians = np.asarray(jax.jit(jax.vmap(hessian))(jnp.asarray(points * scales)))
    size = np.abs(hessians).max(axis=(0, 2, 3))[:, None, None]  # autodiff's rounding
    assert np.all(hessians <= hi + 1e-12 * size)
    assert np.all(hessians >= lo - 1e-12 * size)
    # not vacuous: the enclosure is within 20x of the sampled spread on the mass block
    spread = hessians.max(axis=0) - hessians.min(axis=0)
    assert np.max((hi - lo)[:, :p, :p]) < 20 * np.max(spread[:, :p, :p]) + 1e-9


def test_default_box_divergence_names_the_coulomb_ranges():
    """With the Coulomb sign expanded (``coulomb="taylor"``) the UR5e's whole default box
    diverges within its first 0.1 s (step 8; the Coulomb ranges set it off,
    ``docs/methods.md``): the error says so and names the fix, and the fix works: with
    the Coulomb ranges a tenth as wide (the same layout, so the same compiled program;
    without them the layout and the compile differ) the same run is finite."""
    box = default_box("ur5e")
    params = rmijax.load_robot("ur5e", **box)
    traj = _short(real_arm_case("ur5e").traj, 10)
    message = r"(?s)step 8.*gains\. With Coulomb.*coulomb=.range.*narrow the Coulomb"
    with pytest.raises(rmijax.DivergedError, match=message):
        certified.certified_bounds(traj, params, coulomb="taylor")
    coulomb = box["friction"]["coulomb"]
    assert np.all(coulomb[:, 0] == 0) and np.all(coulomb[:, 1] > 0)
    narrow = dict(box, friction=dict(box["friction"], coulomb=0.1 * coulomb))
    bounds, _ = certified.certified_bounds(
        traj, rmijax.load_robot("ur5e", **narrow), coulomb="taylor"
    )
    assert np.all(np.isfinite(np.asarray(bounds.upper - bounds.lower)))


# --------------------------------------------------------------------------
# coulomb="range": the Coulomb errors move an enclosure of their sign over the tube
# --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def arm2_coulomb(tmp_path_factory):
    """The paper's two-joint arm as a URDF, masses +-5 % and Coulomb ranges 0-10 N m,
    0.5 s of ``hold``/``sine`` (joint 1 held at rest, where the smooth sign is steep),
    certified with ``coulomb="range"`` and ``"auto"``."""
    from arm2_urdf import arm2_urdf

    path = tmp_path_factory.mktemp("arm2") / "arm2.urdf"
    path.write_text(arm2_urdf())
    params = rmijax.load_robot(path, mass=0.05, friction=dict(coulomb=(0.0, 10.0)))
    traj = rmijax.trajectory(["hold", "sine"], duration=0.5)
    runs = {mode: certified.certified_bounds(traj, params, coulomb=mode) for mode in MODES}
    return traj, params, runs


MODES = ("range", "auto")


def _corner_and_draw_states(traj, params):
    """Runs of every corner of the box and 200 uniform draws: (S, T+1, n, 2)."""
    states, _ = rmijax.simulate(traj, params, _samples(params, corners=0, draws=200))
    lo, hi = np.asarray(params.lo), np.asarray(params.hi)
    bits = np.array(np.meshgrid(*[[0, 1]] * lo.size, indexing="ij")).reshape(lo.size, -1).T
    corners, _ = rmijax.simulate(traj, params, np.where(bits == 1, hi, lo))
    return np.concatenate([np.asarray(states), np.asarray(corners)])


@pytest.mark.parametrize("mode", MODES)
def test_coulomb_range_band_contains_samples(arm2_coulomb, mode):
    """None of 216 constant-parameter runs (all 16 corners, 200 uniform draws) leaves the
    band; without the remainder they do (teeth). With ``"auto"`` joint 1 (held at rest,
    its tube narrow) keeps the expansion at most steps and joint 2 takes the range."""
    traj, params, runs = arm2_coulomb
    bounds, cert = runs[mode]
    assert cert.coulomb == mode
    assert np.all(np.isfinite(np.asarray(bounds.upper - bounds.lower)))
    if mode == "auto":
        kept = np.asarray(cert.keep).mean(axis=(0, 1))  # share of steps per joint
        assert kept[0] > 0.5 and kept[1] < 0.5, kept
    else:
        assert cert.keep is None
    states = _corner_and_draw_states(traj, params)
    assert _escape(bounds, states) <= TOL
    bare, _ = certified.certified_bounds(traj, params, coulomb=mode, remainder_scale=0.0)
    assert _escape(bare, states) > 1e-9


def test_coulomb_range_sign_encloses_tanh_over_the_tube():
    """``_sign_range`` holds ``tanh(qd / v_s)`` of every state of the tube it is given
    (the centre plus the polynomial's range plus the remainder), sampled at 2000 points."""
    rng = np.random.default_rng(7)
    n, p = 3, 4
    xc = jnp.asarray(rng.normal(size=(n, 2)) * 0.05)
    sens = jnp.asarray(rng.normal(size=(n, 2, p)) * 0.005)
    sens2 = rng.normal(size=(n, 2, p, p)) * 0.002
    sens2 = jnp.asarray(sens2 + np.swapaxes(sens2, -1, -2))
    d_hi = jnp.asarray(rng.uniform(0.5, 1.0, size=p))
    d_lo = -d_hi
    rhat = jnp.asarray(rng.uniform(0, 0.01, size=(n, 2)))
    lo, hi, keep = certified._sign_range(xc, sens, sens2, d_lo, d_hi, rhat)
    lo, hi = np.asarray(lo), np.asarray(hi)
    assert keep is None
    d = rng.uniform(-1, 1, size=(2000, p))
    r = rng.uniform(-1, 1, size=(2000, n))
    d[::2], r[::2] = np.sign(d[::2]), np.sign(r[::2])  # half of them vertices
    d, r = d * np.asarray(d_hi), r * np.asarray(rhat)[:, 1]
    qd = (
        np.asarray(xc)[:, 1]
        + d @ np.asarray(sens)[:, 1].T
        + 0.5 * np.einsum("kb,ibc,kc->ki", d, np.asarray(sens2)[:, 1], d)
        + r
    )
    sign = np.tanh(qd / rmijax.robots.spatial.COULOMB_VELOCITY)
    assert np.all(sign >= lo) and np.all(sign <= hi)
    # not vacuous: within 1.5x of the sampled spread (measured 1.05-1.31x)
    spread = sign.max(axis=0) - sign.min(axis=0)
    assert np.all(hi - lo <= 1.5 * spread), (hi - lo) / spread


CHECKED = [("interval", "kernel", "range"), ("affine", "carried", "range")]
CHECKED += [("interval", "kernel", "auto"), ("paired_inertia", "carried", "range")]


@pytest.mark.parametrize(("enclosure", "propagate", "mode"), CHECKED)
def test_checker_verifies_a_coulomb_range_certificate(
    arm2_coulomb, enclosure, propagate, mode, monkeypatch
):
    """The checker recomputes the sign's enclosure from its own tube and accepts the first
    steps of a ``coulomb="range"`` or ``"auto"`` certificate (``"auto"``: over these
    steps joint 1 keeps the expansion, joint 2 takes the range from step 2; the checker
    follows ``cert.keep``); it rejects the certificate of a mutant certifier whose
    enclosure is the centre's sign alone (a point: the Coulomb errors' effect then
    ignores how far the tube's velocities spread), and the halved remainder."""
    traj, params, _ = arm2_coulomb
    short = _short(traj, 6)
    options = dict(enclosure=enclosure, propagate=propagate, coulomb=mode)
    _, cert = certified.certified_bounds(short, params, **options)
    if enclosure == "paired_inertia":  # the two mass scales and R paired, not the Coulomb
        layout, p = certified._layout(params), params.n_params
        assert p == 4 and certified.paired_variables(enclosure, layout, 2, p) == (0, 1, 4, 5, 6, 7)
    if mode == "auto":
        keep = np.asarray(cert.keep)[0]
        assert keep[:, 0].all() and not keep[2:, 1].any(), keep
        bad = dataclasses.replace(cert, keep=cert.keep.at[0, 0, 0].set(0.5))
        assert "not 0 or 1" in check_certificate(bad, short, params, steps=1).reason
    result = check_certificate(cert, short, params, steps=5)
    assert result.ok, result.reason
    _, halved = certified.certified_bounds(short, params, remainder_scale=0.5, **options)
    rejected = check_certificate(halved, short, params, steps=5)
    assert not rejected.ok and "below the recomputed bound" in rejected.reason

    def centre_only(xc, sens, sens2, d_lo, d_hi, rhat, auto=False, spread=None):
        sign = jnp.tanh(xc[:, 1] * (1.0 / rmijax.robots.spatial.COULOMB_VELOCITY))
        return sign, sign, jnp.zeros_like(sign) if auto else None

    monkeypatch.setattr(certified, "_sign_range", centre_only)
    certified._certify.clear_cache()  # compiled with the honest enclosure
    try:
        _, mutant = certified.certified_bounds(short, params, **options)
    finally:
        certified._certify.clear_cache()
    rejected = check_certificate(mutant, short, params, steps=5)
    assert not rejected.ok and "below the recomputed bound" in rejected.reason


def test_coulomb_spread_moves_the_choice_and_stays_sound(arm2_coulomb):
    """``coulomb_spread`` sets where ``"auto"`` takes the sign's range: a wider threshold
    keeps the expansion at more steps (the choice moves), and the band still holds every
    sampled run (216) and passes the checker on its first steps; the argument is checked."""
    traj, params, runs = arm2_coulomb
    _, default = runs["auto"]
    bounds, cert = certified.certified_bounds(traj, params, coulomb="auto", coulomb_spread=1.0)
    kept, kept_default = np.asarray(cert.keep).mean(), np.asarray(default.keep).mean()
    assert kept > kept_default, (kept, kept_default)
    states = _corner_and_draw_states(traj, params)
    assert _escape(bounds, states) <= TOL
    short = _short(traj, 6)
    _, early = certified.certified_bounds(short, params, coulomb="auto", coulomb_spread=1e-3)
    assert not np.asarray(early.keep)[0, 1:].all()  # ranges taken on these steps
    result = check_certificate(early, short, params, steps=5)
    assert result.ok, result.reason
    for bad in (0.0, -0.1, float("nan"), "wide"):
        with pytest.raises(ValueError, match="coulomb_spread must be a positive finite"):
            certified.certified_bounds(short, params, coulomb_spread=bad)


def test_default_coulomb_certifies_the_ur5e_default_box_start():
    """The UR5e's whole default box over its first 0.1 s: with the Taylor-expanded sign the
    remainder diverges at step 8 (the test above); with the default ``coulomb="auto"``
    (the sign bounded by its range where the tube's velocities spread wide, which they
    do here) the band is finite, none of 458 sampled runs leaves it, and without the
    remainder they do."""
    params = rmijax.load_robot("ur5e", **default_box("ur5e"))
    traj = _short(real_arm_case("ur5e").traj, 10)
    bounds, cert = certified.certified_bounds(traj, params)
    assert cert.coulomb == "auto"
    keep = np.asarray(cert.keep)
    assert keep.shape == (1, traj.n_steps, 6)
    assert np.any(keep == 0) and np.any(keep == 1)  # both choices made on this run
    assert np.all(np.isfinite(np.asarray(bounds.upper - bounds.lower)))
    states, _ = rmijax.simulate(traj, params, _samples(params))
    states = np.asarray(states)
    assert _escape(bounds, states) <= TOL
    bare, _ = certified.certified_bounds(traj, params, remainder_scale=0.0)
    assert _escape(bare, states) > 1e-9
