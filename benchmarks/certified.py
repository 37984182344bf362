"""Benchmark of the certified bands: time, tightness against the worst case, soundness counts.

For each case:

- time: one call with compile (``seconds``) and a second call (``seconds_warm``);
- soundness: all ``2^p`` corners (``p <= 12``; above, 256 random corners and both ends
  of the box) and ``--draws`` uniform draws run by
  ``rmijax.simulate``, and the ``worst_case`` maximisers at the scored times; the
  count of samples outside the band by more than 1e-12; an attack on the band
  (projected gradient over ``th`` of the slack, with restarts) at the steps where
  the samples came closest, its finds run over the whole horizon;
- tightness: band width / worst-case range (``rmijax.worst_case_table``) at
  times every ``--every`` s after 0.5 s, median and p90 per sensor (and the
  minimum, which must not fall below 1).

With ``--faults``: the paper fault case instead (two-joint arm, ``hold``/``sine``,
the paper's true parameters, every fault kind of the default suite on both
joints at 3 s): latency, misses and false alarms of the ``certified``, ``rmi``
and ``empirical`` bands, and the false alarms of the fault-free run.

With ``--checker``: :func:`rmijax.methods.certificate_check.check_certificate` on every
enclosure/propagate pair (pendulum, two-joint arm, each also with the paired forms;
``preset_arm(4)`` affine/carried; the UR5e's friction box, one step):
accepted, the halved-remainder mutant's certificate rejected, seconds per step and piece.

With ``--injected``: the same rows' certificates (JAX only, no checker), per step the
largest remainder input ``injected`` with the remainder on and off (the rounding padding):
the steps where the halved mutant can differ from the certificate by more than rounding.

With ``--remainder``: how tight the remainder bound is on the tests' pendulum fixture
(``sine``, 1 s, ``splits=2``): the largest true remainder ``|R_k|`` and input ``|xi_k|``
over the corners and 200 draws as a share of the bounds ``r_k`` and ``w_k``, and how far
samples leave the band when the remainder is halved or switched off.

``--enclosure`` and ``--propagate`` choose ``certified``'s enclosure of the Hessian
(interval or affine) and how the remainder is carried (kernel or carried); by default
each is chosen by the number of joints (see :func:`rmijax.certified_bounds`).

Examples::

    PYTHONPATH=src python3 benchmarks/certified.py --cases arm2_hold_sine --duration 15 \\
        --json benchmarks/results/certified_cpu.json
    PYTHONPATH=src python3 benchmarks/certified.py --faults --duration 15 \\
        --json benchmarks/results/certified_faults_cpu.json
    PYTHONPATH=src python3 benchmarks/certified.py --cases preset4_sine --duration 1 \\
        --cold-only --json benchmarks/results/certified_preset4_affine_cpu.json
    PYTHONPATH=src python3 benchmarks/certified.py --cases ur5e_friction ur5e_tenth \\
        --duration 1 --json benchmarks/results/certified_arms_cpu.json
    PYTHONPATH=src python3 benchmarks/certified.py --cases panda_friction --duration 1 \\
        --split 'coulomb[joint4]=2' --cold-only --json out.json

The ``<arm>_friction``, ``<arm>_tenth`` and ``<arm>_box`` cases (``ur5e``, ``panda``,
``iiwa14``) are the arm of :func:`rmijax.load_robot` on the first seconds of the
pick-and-place move of ``rmijax --robot``: the default box's friction ranges alone, a
tenth of the whole default box (mass scales, payload, friction), or all of it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from _common import host_reference, run_meta  # noqa: E402

import rmijax  # noqa: E402
from rmijax.methods.base import DivergedError  # noqa: E402
from rmijax.methods.certified import (  # noqa: E402
    AUTO_MAX_PIECES,
    AUTO_REFINE,
    COULOMB_MODES,
    ENCLOSURES,
    _choice,
    _coulomb_choice,
    _solve_choice,
    certified_bounds,
)

CASES = {
    "arm2_hold_sine": (rmijax.paper_arm2, ["hold", "sine"]),
    "arm2_hold_ramp": (rmijax.paper_arm2, ["hold", "ramp"]),
    "arm2_hold_composite": (rmijax.paper_arm2, ["hold", "composite"]),
    "arm2_slow_sine_composite": (rmijax.paper_arm2, ["slow_sine", "composite"]),
    "pendulum_sine": (rmijax.paper_pendulum, ["sine"]),
    "preset2_sine": (lambda: rmijax.preset_arm(2), ["sine"] * 2),
    "preset4_sine": (lambda: rmijax.preset_arm(4), ["sine"] * 4),
    "preset6_sine": (lambda: rmijax.preset_arm(6), ["sine"] * 6),
}


def _arm_case(name, share=None):
    """A loaded arm on the pick-and-place move of ``rmijax --robot`` (its first
    ``duration`` s): with ``share=None`` the default box's friction ranges only (masses
    and payload certain), else ``share`` of the whole default box (mass scales, payload,
    friction)."""

    def build():
        from rmijax.robots.loaders import default_box

        box = default_box(name)
        if share is None:
            box = dict(friction=box["friction"])
        else:
            box = dict(
                mass=box["mass"] * share,
                payload=(0.0, box["payload"][1] * share),
                friction={kind: pairs * share for kind, pairs in box["friction"].items()},
            )
        return rmijax.load_robot(name, **box)

    def motion(duration):
        from rmijax.apps.real_arm import home_pose, pick_and_place

        traj = pick_and_place(home_pose(name))
        steps = int(round(duration / traj.dt)) + 1
        keys = ("t", "q_d", "qd_d", "qdd_d", "u_d", "x_n", "qdd_n")
        return dataclasses.replace(traj, **{k: getattr(traj, k)[:steps] for k in keys})

    return build, motion


for _arm in ("ur5e", "panda", "iiwa14"):
    CASES[f"{_arm}_friction"] = _arm_case(_arm)
    CASES[f"{_arm}_tenth"] = _arm_case(_arm, 0.1)
    CASES[f"{_arm}_box"] = _arm_case(_arm, 1.0)


def _trajectory(paths, duration):
    """The case's motion: named paths per joint, or a loaded arm's move."""
    return paths(duration) if callable(paths) else rmijax.trajectory(paths, duration=duration)


def _samples(params, draws, seed=0, corners=256):
    """Every corner (``p <= 12``; else ``corners`` random ones and both box ends) and
    ``draws`` uniform draws."""
    lo, hi = np.asarray(params.lo), np.asarray(params.hi)
    rng = np.random.default_rng(seed)
    rows = [lo + (hi - lo) * rng.uniform(size=(draws, lo.size))]
    if params.n_params <= 12:
        rows.insert(0, np.asarray(params.corners))
    else:
        bits = np.random.default_rng(seed + 1).integers(0, 2, size=(corners, lo.size))
        rows.insert(0, np.concatenate([np.where(bits == 1, hi, lo), [lo, hi]]))
    return np.concatenate(rows)


def run_case(name, duration, draws, every, splits, options=None, warm=True):
    builder, paths = CASES[name]
    params = builder()
    traj = _trajectory(paths, duration)
    options = dict(options or {})
    start = time.perf_counter()
    bounds, cert = certified_bounds(traj, params, splits=splits, **options)
    bounds.upper.block_until_ready()
    seconds = time.perf_counter() - start
    seconds_warm = None
    if warm:
        start = time.perf_counter()
        again, _ = certified_bounds(traj, params, splits=splits, **options)
        again.upper.block_until_ready()
        seconds_warm = round(time.perf_counter() - start, 2)
    upper, lower = np.asarray(bounds.upper), np.asarray(bounds.lower)
    times = np.arange(0.5, duration + 1e-9, every)
    steps = np.round(times / traj.dt).astype(int)
    escapes, total = 0, 0
    worst = -np.inf
    samples = _samples(params, draws)
    run_high = np.full(upper.shape, -np.inf)  # (T+1, n, 2) over all samples
    run_low = np.full(upper.shape, np.inf)
    arg_high = np.zeros(upper.shape, int)
    arg_low = np.zeros(upper.shape, int)
    offset = 0
    for chunk in np.array_split(samples, max(1, len(samples) // 256)):
        states = np.asarray(rmijax.simulate(traj, params, chunk)[0])
        out = np.maximum(states - upper, lower - states)
        escapes += int(np.sum(np.any(out > 1e-12, axis=(1, 2, 3))))
        total += len(chunk)
        worst = max(worst, float(out.max()))
        better = states.max(0) > run_high
        arg_high = np.where(better, offset + states.argmax(0), arg_high)
        run_high = np.where(better, states.max(0), run_high)
        better = states.min(0) < run_low
        arg_low = np.where(better, offset + states.argmin(0), arg_low)
        run_low = np.where(better, states.min(0), run_low)
        offset += len(chunk)
    seen_high, seen_low = run_high[steps], run_low[steps]
    table = rmijax.worst_case_table(traj, params, times, random_starts=2, iterations=20)
    assert np.array_equal(steps, table["steps"])
    p = params.n_params
    maximisers = np.concatenate([table["th_low"].reshape(-1, p), table["th_high"].reshape(-1, p)])
    states = np.asarray(rmijax.simulate(traj, params, maximisers)[0])
    out = np.maximum(states - upper, lower - states)
    wc_escapes = int(np.sum(np.any(out > 1e-12, axis=(1, 2, 3))))
    worst = max(worst, float(out.max()))
    reach_high = np.maximum.reduce([table["high"], states[:, steps].max(0), seen_high])
    reach_low = np.minimum.reduce([table["low"], states[:, steps].min(0), seen_low])
    ratio = (upper[steps] - lower[steps]) / (reach_high - reach_low)
    attack = _attack(traj, params, upper, lower, run_high, run_low, arg_high, arg_low, samples)
    worst = max(worst, attack.pop("worst"))
    row = dict(
        case=name,
        n=params.n_joints,
        pieces=int(cert.n_pieces),
        **(dict(splits=splits) if isinstance(splits, dict | str) else {}),
        **(_auto_options(options) if splits == "auto" else {}),
        enclosure=cert.enclosure,
        propagate=cert.propagate,
        solve=cert.solve,
        **(dict(coulomb=cert.coulomb) if cert.coulomb != "taylor" else {}),
        **({"coulomb_spread": options["coulomb_spread"]} if "coulomb_spread" in options else {}),
        segments=int(cert.segments),
        steps=traj.n_steps,
        seconds=round(seconds, 2),
        seconds_warm=seconds_warm,
        samples=total,
        samples_outside=escapes,
        maximisers=len(maximisers),
        maximisers_outside=wc_escapes,
        **attack,
        worst_excess=worst,
    )
    for sensor, label in enumerate(("encoder", "tachometer")):
        r = ratio[..., sensor]
        row[f"{label}_median"] = round(float(np.median(r)), 3)
        row[f"{label}_p90"] = round(float(np.quantile(r, 0.9)), 3)
        row[f"{label}_min"] = round(float(np.min(r)), 3)
    return row


def _taylor_values(cert, piece, d):
    """The second-order model ``x_c + S d + 1/2 Q[d, d]`` of ``cert``'s piece ``piece`` at
    the offsets ``d`` (S, p) from its centre: (S, T+1, n, 2)."""
    return (
        np.asarray(cert.state)[piece][None]
        + np.einsum("tnsp,Sp->Stns", np.asarray(cert.sens)[piece], d)
        + 0.5 * np.einsum("tnspq,Sp,Sq->Stns", np.asarray(cert.sens2)[piece], d, d)
    )


def _split_items(items):
    """``--split NAME=PARTS ...`` as ``{name: parts}``; ``ValueError`` on a bad item."""
    return {k: int(v) for k, v in (item.split("=") for item in items)}


def run_remainder(duration=1.0, splits=2, draws=200):
    """How tight the remainder bound is: the pendulum fixture of the tests (``sine``).

    For each piece, the true remainder ``R_k(th) = x_k(th) - (x_c + S d + 1/2 Q[d, d])``
    of the corners and ``draws`` uniform draws in it (run by ``simulate``), its input
    ``xi_k = R_(k+1) - A R_k``, against the certificate's ``r_k`` and ``w_k``; and how far
    the samples leave the band when the remainder is halved or switched off.
    """
    params = rmijax.paper_pendulum()
    traj = rmijax.trajectory(["sine"], duration=duration)
    bounds, cert = certified_bounds(traj, params, splits=splits)
    samples = _samples(params, draws)
    states = np.asarray(rmijax.simulate(traj, params, samples)[0])  # (S, T+1, n, 2)
    kp, kd, dt = np.asarray(traj.kp), np.asarray(traj.kd), traj.dt
    n = traj.n_joints
    a = np.zeros((n, 2, 2))
    a[:, 0, 0], a[:, 0, 1], a[:, 1, 0], a[:, 1, 1] = 1.0, dt, -kp * dt, 1.0 - kd * dt
    reached_r = np.zeros(np.asarray(cert.remainder).shape)  # (P, T+1, n, 2)
    reached_w = np.zeros(np.asarray(cert.injected).shape)  # (P, T, n, 2)
    for piece in range(cert.n_pieces):
        lo, hi = np.asarray(cert.lo)[piece], np.asarray(cert.hi)[piece]
        inside = np.all((samples >= lo) & (samples <= hi), axis=1)
        d = samples[inside] - np.asarray(cert.center)[piece]
        remainder = states[inside] - _taylor_values(cert, piece, d)
        xi = remainder[:, 1:] - np.einsum("nij,Stnj->Stni", a, remainder[:, :-1])
        reached_r[piece] = np.abs(remainder).max(0)
        reached_w[piece] = np.abs(xi).max(0)
    ratio_r = reached_r / np.maximum(np.asarray(cert.remainder), 1e-300)
    ratio_w = reached_w / np.maximum(np.asarray(cert.injected), 1e-300)
    k0 = int(round(0.5 / traj.dt))
    share = np.asarray(cert.remainder).max(0)[k0:] / np.asarray(bounds.width)[k0:]
    result = dict(case="pendulum_sine", duration=duration, splits=splits, samples=len(samples))
    for sensor, label in enumerate(("encoder", "tachometer")):
        w_part = ratio_w[:, :, :, sensor].max(axis=(0, 2))  # (T,) over pieces and joints
        r_part = ratio_r[:, :, :, sensor].max(axis=(0, 2))
        result[label] = dict(
            input_reached_step0=round(float(w_part[0]), 4),
            input_reached_steps8_96=[
                round(float(w_part[8:97].min()), 5),
                round(float(w_part[8:97].max()), 5),
            ],
            remainder_reached_steps8_96=[
                round(float(r_part[8:97].min()), 5),
                round(float(r_part[8:97].max()), 5),
            ],
            remainder_share_of_width_median=round(float(np.median(share[..., sensor])), 4),
        )
    for scale in (0.5, 0.0):
        mutant, _ = certified_bounds(traj, params, splits=splits, remainder_scale=scale)
        out = np.maximum(states - np.asarray(mutant.upper), np.asarray(mutant.lower) - states)
        where = np.unravel_index(np.argmax(out), out.shape)
        result[f"escape_scale_{scale}"] = dict(
            excess=float(out.max()),
            sample=[float(v) for v in samples[where[0]]],
            step=int(where[1]),
            sensor=("encoder", "tachometer")[int(where[3])],
            steps_with_escape=int(np.sum(np.any(out > 1e-12, axis=(0, 2, 3)))),
        )
    # the same mutation on the two-joint arm (hold / sine, 0.3 s, default 16 pieces)
    arm = rmijax.paper_arm2()
    arm_traj = rmijax.trajectory(["hold", "sine"], duration=0.3)
    arm_samples = _samples(arm, draws)
    arm_states = np.asarray(rmijax.simulate(arm_traj, arm, arm_samples)[0])
    for scale in (1.0, 0.5):
        band, _ = certified_bounds(arm_traj, arm, remainder_scale=scale)
        out = np.maximum(arm_states - np.asarray(band.upper), np.asarray(band.lower) - arm_states)
        result[f"arm2_hold_sine_0.3s_scale_{scale}"] = dict(
            samples=len(arm_samples), worst_excess=float(out.max())
        )
    return result


FAULT_METHODS = ("certified", "rmi", "empirical")


PAIRED = (("paired", "carried"), ("paired_inertia", "carried"))
CHECKER_RUNS = (
    # case, duration (s), splits, pairs, steps checked (None: all), pieces checked
    ("pendulum_sine", 1.0, 2, "all", None, None),
    ("pendulum_sine", 1.0, 2, PAIRED, None, None),
    ("arm2_hold_sine", 1.0, None, "all", 5, "ends"),
    ("arm2_hold_sine", 1.0, None, PAIRED, 5, "ends"),
    ("preset4_sine", 0.05, None, (("affine", "carried"),), 2, "ends"),
    # a real arm: the UR5e's friction box (18 parameters) with the chain's defaults,
    # one step of its one piece (pure Python on a 6-joint chain: minutes per step)
    ("ur5e_friction", 0.02, None, (("affine", "carried"),), 1, "ends"),
)
PAIRS = (
    ("interval", "kernel"),
    ("affine", "carried"),
    ("interval", "carried"),
    ("affine", "kernel"),
)


def _row_certificate(name, duration, options, remainder_scale=1.0):
    """Case ``name``'s motion over ``duration`` s, its parameters, and its certificate
    (``certified_bounds`` with ``options``, the remainder scaled by ``remainder_scale``):
    ``(traj, params, cert, certify s)``."""
    make, paths = CASES[name]
    params = make()
    traj = _trajectory(paths, duration)
    started = time.perf_counter()
    _, cert = certified_bounds(traj, params, remainder_scale=remainder_scale, **options)
    return traj, params, cert, time.perf_counter() - started


def _checker_run(name, duration, options, steps, pieces, remainder_scale=1.0):
    """Certify case ``name`` (its certificate's remainder scaled by ``remainder_scale``)
    and check it: ``(certificate's pieces, pieces checked, CheckResult, certify s, check
    s)``. A function of plain arguments, so that a worker process can run it."""
    from rmijax.methods.certificate_check import check_certificate

    traj, params, cert, certify_s = _row_certificate(name, duration, options, remainder_scale)
    chosen = None if pieces is None else sorted({0, cert.n_pieces // 2})
    count = traj.n_steps if steps is None else steps
    started = time.perf_counter()
    result = check_certificate(cert, traj, params, steps=count, pieces=chosen)
    check_s = time.perf_counter() - started
    checked = cert.n_pieces if chosen is None else len(chosen)
    return cert.n_pieces, checked, result, certify_s, check_s


def _checker_runs(cases=None, steps=None):
    """``CHECKER_RUNS``, of ``cases`` only (all if None), each checking ``steps`` steps
    (the row's own if None; its duration lengthened to hold them, at the default step)."""
    runs = []
    for name, duration, splits, pairs, count, pieces in CHECKER_RUNS:
        if cases is not None and name not in cases:
            continue
        if steps is not None:
            count = steps
            duration = max(duration, (steps + 1) * rmijax.trajectory(["hold"], duration=1.0).dt)
        runs.append((name, duration, splits, pairs, count, pieces))
    if cases is not None and not runs:
        raise ValueError(f"no checker run of {cases}; they are {[r[0] for r in CHECKER_RUNS]}")
    return runs


def run_checker(cases=None, steps=None, jobs=1):
    """The independent checker on each enclosure/propagate pair: does it accept the
    certificate, does it reject the halved-remainder mutant's, and how long it takes.

    Pieces ``"ends"``: the first and the middle one (the one piece, if it is alone).
    Times are seconds per checked step and piece (pure Python ``mpmath``, one core).
    ``cases`` and ``steps`` choose rows and override their steps checked
    (:func:`_checker_runs`); ``jobs=2`` checks the certificate and its mutant in two
    processes at once (each on one core; their seconds are then those of a loaded host).
    """
    from concurrent.futures import ProcessPoolExecutor

    rows = []
    for name, duration, splits, pairs, steps_, pieces in _checker_runs(cases, steps):
        for enclosure, propagate in PAIRS if pairs == "all" else pairs:
            options = dict(splits=splits, enclosure=enclosure, propagate=propagate)
            runs = [(name, duration, options, steps_, pieces, scale) for scale in (1.0, 0.5)]
            if jobs > 1:
                with ProcessPoolExecutor(2, mp_context=_spawn()) as pool:
                    done = list(pool.map(_checker_run, *zip(*runs, strict=True)))
            else:
                done = [_checker_run(*run) for run in runs]
            (n_pieces, checked, result, certify_s, check_s), (*_, rejected, _, _) = done
            row = dict(
                case=name,
                duration=duration,
                enclosure=enclosure,
                propagate=propagate,
                pieces=n_pieces,
                pieces_checked=checked,
                steps_checked=result.steps,
                accepted=bool(result.ok),
                reason=result.reason,
                halved_rejected=not rejected.ok,
                halved_reason=rejected.reason,
                halved_steps_checked=rejected.steps,
                certify_seconds=round(certify_s, 1),
                check_seconds=round(check_s, 1),
                seconds_per_step_piece=round(check_s / max(result.steps * checked, 1), 3),
                jobs=jobs,
            )
            rows.append(row)
            print(
                f"{name:16} {enclosure:>8}/{propagate:<7} pieces {checked}/{n_pieces} "
                f"steps {result.steps:>3} accepted {row['accepted']!s:5} "
                f"halved rejected {row['halved_rejected']!s:5} "
                f"{row['seconds_per_step_piece']:.3f} s/step/piece",
                flush=True,
            )
    return dict(runs=rows)


def run_injected(cases=None, steps=None):
    """Where each checker row's remainder input ``w_k`` starts to count: per step, the
    largest entry of the certificate's ``injected`` with the remainder switched off
    (``remainder_scale=0``: the rounding padding alone, over that run's thinner tube) and
    on (1), over the row's pieces, joints and sensors. The halved mutant
    (``remainder_scale=0.5``) differs from the certificate by about half the difference,
    so the checker can reject it only at steps where that difference is well above the
    padding. ``cases``, ``steps``: as
    :func:`_checker_runs`; the JAX certifier only, no checker (seconds, not minutes).
    """
    rows = []
    for name, duration, splits, pairs, steps_, _ in _checker_runs(cases, steps):
        enclosure, propagate = (PAIRS if pairs == "all" else pairs)[0]
        options = dict(splits=splits, enclosure=enclosure, propagate=propagate)
        injected = {}
        for scale in (0.0, 1.0):
            traj, _, cert, _ = _row_certificate(name, duration, options, scale)
            injected[scale] = np.asarray(cert.injected)  # (P, T, n, 2)
        count = traj.n_steps if steps_ is None else min(steps_, traj.n_steps)
        padding = injected[0.0].max(axis=(0, 2, 3))[:count]
        full = injected[1.0].max(axis=(0, 2, 3))[:count]
        rows.append(
            dict(
                case=name,
                duration=duration,
                enclosure=enclosure,
                propagate=propagate,
                steps=[
                    dict(step=k, padding=float(padding[k]), injected=float(full[k]))
                    for k in range(count)
                ],
            )
        )
        for k in range(count):
            print(
                f"{name:16} step {k:>3} padding {padding[k]:.3e} injected {full[k]:.3e}",
                flush=True,
            )
    return dict(runs=rows)


def _spawn():
    import multiprocessing

    return multiprocessing.get_context("spawn")  # not fork: JAX's threads are running


def run_faults(duration, onset=3.0):
    """The default fault suite on the paper fault case against each method's band."""
    from rmijax.apps.experiments import fault_table, paper_true_parameters
    from rmijax.detection.suite import default_fault_suite

    params = rmijax.paper_arm2()
    traj = rmijax.trajectory(["hold", "sine"], duration=duration)
    th_true = paper_true_parameters(params)
    bands, seconds = {}, {}
    for method in FAULT_METHODS:
        start = time.perf_counter()
        bands[method] = rmijax.bounds(traj, params, method=method)
        bands[method].upper.block_until_ready()
        seconds[method] = round(time.perf_counter() - start, 2)
    _, y_free = rmijax.simulate(traj, params, th_true)
    free = {m: int(rmijax.detect(y_free, b).false_alarms) for m, b in bands.items()}
    rows = []
    for row in fault_table(traj, params, th_true, bands, default_fault_suite(2, onset)):
        entry = dict(fault=row.fault.label)
        for method, found in row.results.items():
            entry[method] = dict(
                latency_s=None if found.latency is None else round(found.latency, 4),
                false_alarms=int(found.false_alarms),
                alarm_output=found.describe_output(found.alarm_output),
                true_exit_s=None if found.true_exit is None else round(found.true_exit, 4),
            )
        rows.append(entry)
    summary = {}
    for method in FAULT_METHODS:
        latencies = [r[method]["latency_s"] for r in rows]
        caught = [v for v in latencies if v is not None]
        summary[method] = dict(
            band_seconds=seconds[method],
            detected=len(caught),
            missed=len(rows) - len(caught),
            median_latency_s=float(np.median(caught)) if caught else None,
            false_alarms_fault_runs=int(sum(r[method]["false_alarms"] for r in rows)),
            false_alarms_fault_free=free[method],
            mean_width=np.asarray(bands[method].width).mean(axis=(0, 1)).round(6).tolist(),
        )
    return dict(case="arm2_hold_sine", duration=duration, onset=onset, summary=summary, rows=rows)


def _print_faults(result):
    print(f"{'fault':28}" + "".join(f"{m:>12}" for m in FAULT_METHODS))
    for row in result["rows"]:
        cells = []
        for method in FAULT_METHODS:
            latency = row[method]["latency_s"]
            cells.append("miss" if latency is None else f"{latency:.2f} s")
        print(f"{row['fault']:28}" + "".join(f"{c:>12}" for c in cells))
    for method, s in result["summary"].items():
        print(
            f"{method}: detected {s['detected']}/{s['detected'] + s['missed']}, median latency "
            f"{s['median_latency_s']} s, false alarms {s['false_alarms_fault_runs']} (faulty runs) "
            f"{s['false_alarms_fault_free']} (fault-free), band {s['band_seconds']} s"
        )


def _attack(traj, params, upper, lower, run_high, run_low, arg_high, arg_low, samples, count=8):
    """An attack on the band where it is tightest: projected gradient over ``th`` of the slack.

    At ``count`` steps (after 0.1 s, 0.2 s apart) where the corners and draws came closest to the
    band (smallest slack ``min(upper - y, y - lower)`` relative to the width, over all
    outputs), ``worst_case_table`` minimises the slack of every output (maximising
    ``y`` minimises ``upper - y``, minimising it ``y - lower``) from the samples that
    came closest, the corners (``p <= 6``) and 4 random starts, 40 iterations; every
    parameter it returns is run over the whole horizon by ``simulate``.
    """
    width = np.maximum(upper - lower, 1e-300)
    slack = np.minimum(upper - run_high, run_low - lower) / width  # (T+1, n, 2)
    first = int(round(0.1 / traj.dt))
    per_step = slack[first:].reshape(slack.shape[0] - first, -1).min(axis=1)
    chosen = []
    for k in first + np.argsort(per_step):  # the tightest steps, at least 0.2 s apart
        if all(abs(k - c) * traj.dt >= 0.2 for c in chosen):
            chosen.append(int(k))
        if len(chosen) == count:
            break
    steps = np.sort(np.asarray(chosen))
    rows = np.unique(np.concatenate([arg_high[steps].ravel(), arg_low[steps].ravel()]))
    starts = samples[rows[:32]]
    table = rmijax.worst_case_table(
        traj, params, steps * traj.dt, starts=starts, random_starts=4, iterations=40
    )
    p = params.n_params
    found = np.concatenate([table["th_low"].reshape(-1, p), table["th_high"].reshape(-1, p)])
    states = np.asarray(rmijax.simulate(traj, params, found)[0])
    out = np.maximum(states - upper, lower - states)
    reached = np.minimum(upper[steps] - table["high"], table["low"] - lower[steps])
    return dict(
        attack_steps=[int(k) for k in steps],
        attack_runs=len(found),
        attack_outside=int(np.sum(np.any(out > 1e-12, axis=(1, 2, 3)))),
        attack_min_slack_rel=float(np.min(reached / width[steps])),
        worst=float(out.max()),
    )


def _auto_options(options):
    """``max_pieces`` and ``refine`` of a ``splits="auto"`` run, the defaults filled in."""
    return dict(
        max_pieces=options.get("max_pieces", AUTO_MAX_PIECES),
        refine=options.get("refine", AUTO_REFINE),
    )


def _splits_arg(text):
    """``--splits``: a count, or ``auto``."""
    if text == "auto":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a count or 'auto', got {text!r}") from None


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=list(CASES)[:4], choices=list(CASES))
    parser.add_argument("--duration", type=float, default=15.0, help="run length in s")
    parser.add_argument("--draws", type=int, default=1000, help="uniform parameter draws")
    parser.add_argument("--every", type=float, default=0.5, help="scored times, every s")
    parser.add_argument(
        "--splits",
        type=_splits_arg,
        default=None,
        help="mass splits, or 'auto' (bisection; see --max-pieces, --refine); default: "
        "the method's",
    )
    parser.add_argument("--max-pieces", type=int, default=None, help="with --splits auto")
    parser.add_argument("--refine", type=float, default=None, help="with --splits auto")
    parser.add_argument(
        "--split",
        nargs="+",
        metavar="NAME=PARTS",
        help="parts per named parameter, e.g. 'coulomb[joint4]=2' (instead of --splits)",
    )
    parser.add_argument("--enclosure", choices=ENCLOSURES, default=None, help="default: auto")
    parser.add_argument(
        "--propagate", choices=("kernel", "carried"), default=None, help="default: auto"
    )
    parser.add_argument(
        "--segments", type=int, default=3, help="radial segments of the Lagrange remainder"
    )
    parser.add_argument(
        "--solve",
        choices=("articulated", "preconditioned"),
        default=None,
        help="how the jets solve M gv = f (default: articulated on the planar arm, "
        "preconditioned on a chain)",
    )
    parser.add_argument(
        "--coulomb",
        choices=COULOMB_MODES,
        default="auto",
        help="how a chain's Coulomb ranges enter the jets (certified_bounds' coulomb)",
    )
    parser.add_argument(
        "--coulomb-spread",
        type=float,
        help="with --coulomb auto: the tube's velocity spread (rad/s) above which a "
        "joint's sign is bounded by its range (certified_bounds' coulomb_spread; "
        "default its own, 0.1)",
    )
    parser.add_argument(
        "--cold-only", action="store_true", help="time one call only (no warm second call)"
    )
    parser.add_argument("--json", help="write the results to this JSON file")
    parser.add_argument(
        "--faults", action="store_true", help="run the fault suite on the paper fault case"
    )
    parser.add_argument(
        "--remainder", action="store_true", help="measure how tight the remainder bound is"
    )
    parser.add_argument(
        "--checker", action="store_true", help="run the certificate checker on every pair"
    )
    parser.add_argument(
        "--injected",
        action="store_true",
        help="per step, the checker rows' remainder input against the rounding padding",
    )
    parser.add_argument(
        "--checker-cases",
        nargs="+",
        help="with --checker or --injected: only these rows (case names)",
    )
    parser.add_argument(
        "--checker-steps",
        type=int,
        help="with --checker or --injected: steps checked in each row",
    )
    parser.add_argument(
        "--jobs",
        type=int,
        default=1,
        choices=(1, 2),
        help="with --checker: 2 checks the certificate and its mutant at once",
    )
    args = parser.parse_args(argv)
    if args.splits != "auto" and (args.max_pieces is not None or args.refine is not None):
        parser.error("--max-pieces and --refine go with --splits auto")
    if args.split:
        if args.splits is not None:
            parser.error("give --splits or --split, not both")
        try:
            args.splits = _split_items(args.split)
        except ValueError:
            parser.error(f"--split takes NAME=PARTS items, got {args.split}")
    if args.checker and args.injected:
        parser.error("give --checker or --injected, not both")
    if not (args.checker or args.injected) and (args.checker_cases or args.checker_steps):
        parser.error("--checker-cases and --checker-steps go with --checker or --injected")
    if not args.checker and args.jobs > 1:
        parser.error("--jobs goes with --checker")
    if args.checker_steps is not None and args.checker_steps < 1:
        parser.error("--checker-steps must be at least 1")
    if args.checker or args.injected:
        try:
            if args.checker:
                result = run_checker(args.checker_cases, args.checker_steps, args.jobs)
            else:
                result = run_injected(args.checker_cases, args.checker_steps)
        except ValueError as error:
            parser.error(str(error))
        if args.json:
            record = dict(meta=run_meta("benchmarks/certified.py", dtype="float64"), **result)
            with open(args.json, "w") as handle:
                json.dump(record, handle, indent=1)
        return result
    if args.remainder:
        result = run_remainder()
        print(json.dumps(result, indent=1))
        if args.json:
            record = dict(meta=run_meta("benchmarks/certified.py", dtype="float64"), **result)
            with open(args.json, "w") as handle:
                json.dump(record, handle, indent=1)
        return result
    if args.faults:
        result = run_faults(args.duration)
        _print_faults(result)
        if args.json:
            record = dict(meta=run_meta("benchmarks/certified.py", dtype="float64"), **result)
            with open(args.json, "w") as handle:
                json.dump(record, handle, indent=1)
        return result
    rows = []
    header = (
        f"{'case':26} {'n':>2} {'pcs':>4} {'time s':>8} {'out/samples':>12} {'out/wc':>7} "
        f"{'out/atk':>7} "
        f"{'enc med':>8} {'enc p90':>8} {'tach med':>8} {'tach p90':>8}"
    )
    print(header, flush=True)
    for name in args.cases:
        started = time.perf_counter()
        try:
            options = dict(
                enclosure=args.enclosure,
                propagate=args.propagate,
                segments=args.segments,
                solve=args.solve,
            )
            options["coulomb"] = args.coulomb
            if args.coulomb_spread is not None:
                options["coulomb_spread"] = args.coulomb_spread
            if args.max_pieces is not None:
                options["max_pieces"] = args.max_pieces
            if args.refine is not None:
                options["refine"] = args.refine
            row = run_case(
                name,
                args.duration,
                args.draws,
                args.every,
                args.splits,
                options,
                warm=not args.cold_only,
            )
        except DivergedError as err:  # the bound blew up: record where, and go on
            seconds = round(time.perf_counter() - started, 2)
            row = dict(case=name, diverged=str(err), seconds=seconds)
            if isinstance(args.splits, dict | str):
                row["splits"] = args.splits
            row |= _auto_options(options) if args.splits == "auto" else {}
            params = CASES[name][0]()  # the options the default chooses for it
            n = params.n_joints
            row |= dict(
                enclosure=_choice("enclosure", args.enclosure, ENCLOSURES, n),
                propagate=_choice("propagate", args.propagate, ("kernel", "carried"), n),
                segments=args.segments,
                solve=_solve_choice(args.solve, params),
            )
            # what the run chose (taylor where there are no Coulomb ranges); rows without
            # the field are taylor (the default before stop 36)
            coulomb = _coulomb_choice(args.coulomb, params)
            row |= dict(coulomb=coulomb) if coulomb != "taylor" else {}
            if "coulomb_spread" in options:
                row["coulomb_spread"] = options["coulomb_spread"]
            rows.append(row)
            print(f"{name:26} diverged after {row['seconds']} s: {err}", flush=True)
            if args.json:
                _write(args, rows)
            continue
        rows.append(row)
        print(
            f"{name:26} {row['n']:>2} {row['pieces']:>4} {row['seconds']:>8.1f} "
            f"{row['samples_outside']:>5}/{row['samples']:<6} {row['maximisers_outside']:>3}/"
            f"{row['maximisers']:<3} {row['attack_outside']:>3}/{row['attack_runs']:<3} "
            f"{row['encoder_median']:>8} {row['encoder_p90']:>8} "
            f"{row['tachometer_median']:>8} {row['tachometer_p90']:>8}",
            flush=True,
        )
        if args.json:
            _write(args, rows)
    return rows


def _write(args, rows):
    # the host's speed as each case ends (stop 52 on): one commit's first call took 292 s
    # and 834 s on two days' 2-core hosts, so seconds compare only with it
    meta = run_meta("benchmarks/certified.py", dtype="float64")
    record = dict(meta={**meta, "host_reference": host_reference()}, rows=rows)
    with open(args.json, "w") as handle:
        json.dump(record, handle, indent=1)


if __name__ == "__main__":
    main()
