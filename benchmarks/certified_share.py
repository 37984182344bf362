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

With ``--inputs`` (loaded arms only; :func:`inputs_row`) it asks instead where the
remainder radius loses against the true remainder: in the enclosure of each step's input,
or in carrying the steps' inputs as independent generators (about 10 minutes on 2 cores
for the UR5e's box in 4):

    python benchmarks/certified_share.py --inputs --cases ur5e_box --split payload_mass=4 \\
        --json benchmarks/results/certified_inputs_cpu.json

With ``--products`` (loaded arms only; :func:`products_row`) it asks where the affine
Hessian's width over the tube comes from at the run's last step: the forms' error terms
against their linear parts, with the products' quadratic part bounded as the certifier
does, by the plain product of radii, dropped, and carried (``enclosure="paired"``'s
forms; about 5 minutes on 2 cores for half a second of the UR5e's box in 4):

    python benchmarks/certified_share.py --products --cases ur5e_box --duration 0.5 \\
        --split payload_mass=4 --json benchmarks/results/certified_products_cpu.json
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time
import types

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(pathlib.Path(__file__).parent))

import jax.numpy as jnp  # noqa: E402
from _common import run_meta  # noqa: E402
from certified import CASES, _samples, _split_items, _taylor_values, _trajectory  # noqa: E402

import rmijax  # noqa: E402
from rmijax import _affine  # noqa: E402
from rmijax.control import closed_loop_step, coupled_perturbation  # noqa: E402
from rmijax.methods import certified as _certified  # noqa: E402
from rmijax.methods.certified import _certify_box, _poly_range, certified_bounds  # noqa: E402

POINTS = 3000  # polynomial evaluations per piece: half random corners, half uniform draws

ARMS = ("ur5e", "panda", "iiwa14")

INPUT_SAMPLES = 200  # --inputs: random corners of each piece, and as many uniform draws

BLOCK_GROUPS = {
    "first_order": [0],
    "parameter_parameter": [1, 2, 4, 5],
    "parameter_remainder": [3, 6, 7, 8],
    "remainder_remainder": [9],
}
"""``--inputs``: ``certified``'s ``w_blocks`` (``linear``, then the quadratic term's
blocks ``mm, ml, mx, lm, ll, lx, xm, xl, xx``; on a chain ``m`` the mass scales, ``l``
the payload and friction, ``x`` the remainder) grouped by what they couple."""

REST_PARTS = ("carried_bounded", "coefficient_radius", "rest")
"""``--inputs``: the rest of ``w_k`` (``certified``'s ``w_rest``): the carried propagation's
bounded terms (the centre Hessian's remainder-remainder block, the parameters' products
with the carried remainder), the stored coefficients' enclosure radius over ``dt`` (their
rounding, and with ``coulomb="auto"`` the Coulomb sign's range where the tube's
velocities spread wide), and what is left (the inflation factors: the checker's margin of
1e-7 and a few ulps)."""


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


def _closed_loop_jacobian(traj, params):
    """``A_c(k)`` (T, 2n, 2n): the state Jacobian of one explicit-Euler step of the closed
    loop at ``(x, th)`` (jitted, vmapped over steps; rows ``(joint, q/qd)``)."""
    model, nominal, kp, kd, dt = params.model, params.nominal, traj.kp, traj.kd, traj.dt

    def step(x, th, u):
        gv = coupled_perturbation(model, th, nominal, x[:, 0], x[:, 1], u, kp, kd)
        return jnp.stack(closed_loop_step(x[:, 0], x[:, 1], u, gv, kp, kd, dt), axis=1)

    jac = jax.jit(jax.vmap(jax.jacfwd(step, 0), (0, None, 0)))
    n = traj.n_joints
    return lambda xc, th: np.asarray(jac(jnp.asarray(xc), jnp.asarray(th), traj.u_d[:-1])).reshape(
        -1, 2 * n, 2 * n
    )


def inputs_row(name, duration, splits, coulomb="auto", seed=0):
    """Where the remainder radius loses against the true remainder, on a loaded arm.

    The remainder obeys ``R_(k+1) = A_c(k) R_k + xi_k`` (``A_c`` the piece centre's
    closed-loop Jacobian); the certificate bounds each step's input ``|xi_k| <= w_k`` and
    carries each step's bound as its own independent generators (their signs free from
    step to step). Sampled per piece (``INPUT_SAMPLES`` random corners and as many uniform
    draws, runs of ``simulate``): the true remainder ``R_k(th)`` (its largest size a
    lower bound of what ``r_k`` must cover), the true inputs ``xi_k(th)``, and ``rho_k``:
    the largest sampled input of every step, ``max_th |xi_j(th)|``, carried the
    certificate's way (``A_c`` products, independent generators per step). Then
    ``r_k / true`` splits into ``rho_k / true`` (what independent per-step inputs cost
    when each is the sampled truth) times ``r_k / rho_k`` (what the enclosure of the
    inputs costs, its feedback through the tube included), and ``w_k / max |xi_k|`` (the
    tachometer rows: the velocity row carries the dynamics) is that enclosure step by
    step. Also the share of ``w_k`` by block (:data:`BLOCK_GROUPS`) and of the rest of
    it (:data:`REST_PARTS`). Median (p90)
    over steps from 0.5 s, joints and pieces. Chains only (their default pair:
    affine/carried, preconditioned solve).
    """
    build, paths = CASES[name]
    params = build()
    traj = _trajectory(paths, duration)
    n, dt = traj.n_joints, traj.dt
    zeros = jnp.zeros((n, 2))
    start = time.perf_counter()
    options = dict(enclosure="affine", propagate="carried", solve="preconditioned")
    centers, los, his, pieces, *_ = _certify_box(
        traj, params, zeros, zeros, splits, diagnostics=True, coulomb=coulomb, **options
    )
    pieces = {key: np.asarray(value) for key, value in pieces.items()}
    seconds = round(time.perf_counter() - start, 1)
    if not np.all(np.isfinite(pieces["remainder"])):
        raise SystemExit(f"{name}: the remainder diverged; --inputs needs a finite one")
    centers, los, his = (np.asarray(a) for a in (centers, los, his))
    coefficients = types.SimpleNamespace(**pieces)  # state, sens, sens2 as a certificate's
    jacobian = _closed_loop_jacobian(traj, params)
    rng = np.random.default_rng(seed)
    first = int(round(0.5 / dt))
    parts = {key: [] for key in ("cert", "indep", "enclosure", "w_over_seen")}
    shares = {key: [] for key in list(BLOCK_GROUPS) + list(REST_PARTS)}
    for i in range(centers.shape[0]):
        lo, hi = los[i], his[i]
        bits = rng.integers(0, 2, size=(INPUT_SAMPLES, lo.size)).astype(bool)
        draws = lo + (hi - lo) * rng.uniform(size=(INPUT_SAMPLES, lo.size))
        ths = np.concatenate([np.where(bits, hi, lo), draws])
        runs = np.asarray(rmijax.simulate(traj, params, ths)[0])  # (S, T+1, n, 2)
        model = _taylor_values(coefficients, i, ths - centers[i])
        rem = (runs - model).reshape(len(ths), -1, 2 * n)  # (S, T+1, 2n)
        a_c = jacobian(pieces["state"][i][:-1], centers[i])  # (T, 2n, 2n)
        xi = rem[:, 1:] - np.einsum("tij,stj->sti", a_c, rem[:, :-1])
        seen_w, true = np.abs(xi).max(0), np.abs(rem).max(0)  # (T, 2n), (T+1, 2n)
        gens, rho = np.zeros((2 * n, 0)), np.zeros_like(true)
        for k in range(a_c.shape[0]):  # the sampled inputs carried as the certificate does
            gens = np.concatenate([a_c[k] @ gens, np.diag(seen_w[k])], axis=1)
            rho[k + 1] = np.abs(gens).sum(1)
        radius = pieces["remainder"][i].reshape(-1, 2 * n)
        w = pieces["injected"][i].reshape(-1, 2 * n)
        tiny = 1e-300
        parts["cert"].append((radius / np.maximum(true, tiny))[first:])
        parts["indep"].append((rho / np.maximum(true, tiny))[first:])
        parts["enclosure"].append((radius / np.maximum(rho, tiny))[first:])
        parts["w_over_seen"].append((w / np.maximum(seen_w, tiny))[first - 1 :])
        total = pieces["injected"][i][first - 1 :, :, 1] / dt  # (T', n): w_k, rounding in
        blocks = pieces["w_blocks"][i][first - 1 :] / total[..., None]
        for key, cols in BLOCK_GROUPS.items():
            shares[key].append(blocks[..., cols].sum(-1))
        rest = pieces["w_rest"][i][first - 1 :] / total[..., None]  # (T', n, 2)
        shares["carried_bounded"].append(rest[..., 0])
        shares["coefficient_radius"].append(rest[..., 1])
        shares["rest"].append(1.0 - blocks.sum(-1) - rest.sum(-1))
    row = dict(
        case=name,
        duration=duration,
        splits=splits,
        coulomb=coulomb,
        pieces=int(centers.shape[0]),
        samples_per_piece=2 * INPUT_SAMPLES,
        seconds=seconds,
    )
    for s, sensor in ((0, "encoder"), (1, "tachometer")):
        for key in ("cert", "indep", "enclosure"):
            values = np.stack(parts[key])[..., s::2]
            row[f"{sensor}_{key}"] = _median_p90(values.ravel())
    row["tachometer_w_over_seen"] = _median_p90(np.stack(parts["w_over_seen"])[..., 1::2].ravel())
    row["w_share"] = {key: _median_p90(np.stack(v).ravel()) for key, v in shares.items()}
    return row


PRODUCT_VARIANTS = ("certifier", "plain", "no_quadratic")
"""``--products``: the affine product's quadratic part as the certifier bounds it (the
product of radii intersected with the polarisation bound, centred), as the plain product
of radii (the bound before stop 45), and dropped (not sound: only to attribute the error
term to it). Also measured: ``"paired"`` (``enclosure="paired"``'s forms, whose products
carry their first-order parts in pair symbols: their ``lin`` holds those symbols'
coefficients too, so compare ``rad``, the forms' whole radius ``lin + e``) and
``"paired_inertia"`` (``enclosure="paired_inertia"``'s: pair symbols for the mass
scales, the payload and the remainder only, ``paired_variables``)."""

PAIRED_VARIANTS = ("paired", "paired_inertia")


def _plain_bilinear(x, o, rad_x, rad_y):
    return jnp.zeros_like(rad_x), _affine._up(rad_x * rad_y)


def _no_bilinear(x, o, rad_x, rad_y):
    return jnp.zeros_like(rad_x), jnp.zeros_like(rad_x)


def products_row(name, duration, splits, coulomb="auto"):
    """Where the affine Hessian's width over the tube comes from, at the last step.

    Certifies ``name`` over ``duration`` s (affine jets, carried propagation, the
    preconditioned solve: the chains' default), then at the last step of every piece
    encloses ``gv``'s Hessian over the piece's tube (``_evaluate_affine``, the whole box
    ``s = 1``) with each product variant (:data:`PRODUCT_VARIANTS`) and sums, over the
    parameter-parameter block and over every block, ``sum_ab X_ab v_a v_b`` (``v`` the
    variables' radii: the piece's half-widths, ``r_k``) for ``X`` the forms' error terms
    ``e`` and their linear parts ``sum_i |a_i|``: the error term is the nonlinear operations'
    remainders, the linear part the first-order variation over the tube. Medians over
    pieces and joints (rad/s^2).
    """
    build, paths = CASES[name]
    params = build()
    traj = _trajectory(paths, duration)
    n = traj.n_joints
    zeros = jnp.zeros((n, 2))
    start = time.perf_counter()
    options = dict(enclosure="affine", propagate="carried", solve="preconditioned")
    centers, los, his, pieces, *_ = _certify_box(
        traj, params, zeros, zeros, splits, coulomb=coulomb, **options
    )
    pieces = {key: np.asarray(value) for key, value in pieces.items()}
    seconds = round(time.perf_counter() - start, 1)
    if not np.all(np.isfinite(pieces["remainder"])):
        raise SystemExit(f"{name}: the remainder diverged; --products needs a finite one")
    free = _certified._free_parameters(params)
    rows = np.arange(params.n_params) if free is None else np.asarray(free)
    fixed = jnp.asarray(np.asarray(params.lo))
    matrix_fn = _certified.solve_matrix(params)
    layout = _certified._layout(params)
    k = pieces["state"].shape[1] - 1
    p = rows.size
    sums = {
        f"{v}_{part}_{block}": []
        for v in PRODUCT_VARIANTS + PAIRED_VARIANTS
        for part in ("e", "lin", "rad")
        for block in ("dd", "all")
    }
    centers, los, his = (np.asarray(a) for a in (centers, los, his))
    for i in range(centers.shape[0]):
        center = jnp.asarray(centers[i][rows])
        d_lo = jnp.minimum(jnp.asarray(los[i][rows]) - center, 0.0)
        d_hi = jnp.maximum(jnp.asarray(his[i][rows]) - center, 0.0)
        d_rad = jnp.maximum(-d_lo, d_hi)
        xc = jnp.asarray(pieces["state"][i, k])
        sens = jnp.asarray(pieces["sens"][i, k][..., rows])
        sens2 = jnp.asarray(pieces["sens2"][i, k][..., rows[:, None], rows[None, :]])
        rhat = jnp.asarray(pieces["remainder"][i, k])
        consts = _certified._step_consts(
            xc, sens, sens2, center, d_lo, d_hi, rhat, traj.u_d[k], params.nominal, traj.kp,
            traj.kd, fixed, matrix_fn=matrix_fn, free=free, coulomb=coulomb,
        )  # fmt: skip
        v = np.concatenate([np.asarray(d_rad), np.asarray(rhat).reshape(-1)])
        weight = v[:, None] * v[None, :]
        bilinears = (_affine._bilinear, _plain_bilinear, _no_bilinear) + (_affine._bilinear,) * 2
        variants = PRODUCT_VARIANTS + PAIRED_VARIANTS
        for variant, bilinear in zip(variants, bilinears, strict=True):
            pairing = _certified.paired_variables(variant, layout, n, p, free)
            forms = _hessian_forms(
                xc, sens, sens2, center, d_rad, rhat, consts, layout, free, bilinear,
                paired=pairing or False,
            )  # fmt: skip
            lin = np.abs(forms.a).sum(-1)
            for part, values in (("e", forms.e), ("lin", lin), ("rad", lin + forms.e)):
                weighted = np.asarray(values) * weight  # (n, m, m)
                sums[f"{variant}_{part}_dd"].append(weighted[:, :p, :p].sum((1, 2)))
                sums[f"{variant}_{part}_all"].append(weighted.sum((1, 2)))
    row = dict(
        case=name,
        duration=duration,
        splits=splits,
        coulomb=coulomb,
        pieces=int(centers.shape[0]),
        step=int(k),
        seconds=seconds,
    )
    for key, values in sums.items():
        row[key] = float(np.median(np.concatenate(values)))
    return row


def _hessian_forms(
    xc, sens, sens2, center, d_rad, rhat, consts, layout, free, bilinear, paired=False
):
    """The affine forms of ``gv``'s Hessian over the tube (``_evaluate_affine``'s, before
    their bounds), with ``bilinear`` as the products' quadratic part (``paired``: the
    :class:`rmijax._affine.PairedForm` ones, which carry it instead)."""
    captured = {}
    run = _certified.run_affine_tape

    def capture(*args):
        value, grad, hess = run(*args)
        captured["h"] = hess
        return value, grad, hess

    saved = _affine._bilinear
    try:
        _affine._bilinear = bilinear
        _certified.run_affine_tape = capture
        _certified._evaluate_affine(
            xc, sens, sens2, center, d_rad, rhat, None, 1.0, consts, layout, free, paired
        )
    finally:
        _affine._bilinear = saved
        _certified.run_affine_tape = run
    h = captured["h"]
    return types.SimpleNamespace(a=np.asarray(h.a), e=np.asarray(h.e))


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
    parser.add_argument(
        "--inputs",
        action="store_true",
        help="instead: split the remainder's looseness into its inputs' enclosure and "
        "their independent carrying (inputs_row; loaded arms only)",
    )
    parser.add_argument(
        "--products",
        action="store_true",
        help="instead: where the affine Hessian's width over the tube comes from, by "
        "product variant (products_row; loaded arms only)",
    )
    args = parser.parse_args(argv)
    if (args.inputs or args.products) and any(
        name.split("_")[0] not in ARMS for name in args.cases
    ):
        parser.error(
            "--inputs and --products take the loaded arms' cases only (ur5e_*, panda_*, iiwa14_*)"
        )
    try:
        splits = _split_items(args.split) or None
    except ValueError:
        parser.error(f"--split takes NAME=PARTS items, got {args.split}")
    rows = []
    for name in args.cases:
        row = products_row if args.products else inputs_row if args.inputs else share_row
        rows.append(row(name, args.duration, splits))
        print(json.dumps(rows[-1]), flush=True)
        if args.json:
            meta = run_meta("benchmarks/certified_share.py", dtype="float64")
            record = dict(meta=meta, rows=rows)
            with open(args.json, "w") as handle:
                json.dump(record, handle, indent=1)


if __name__ == "__main__":
    main()
