"""Hostile-input probe: feed bad inputs to the public API and the CLI, print what each gets.

Issue 13's probe, re-runnable: every row is an input a new user might try and
the answer rmijax gives now: ``refused`` (the exception type and the first
line of its message), ``flagged`` (an answer that says what is wrong) or
``accepted`` (a plain answer: for a hostile input that is a finding).

    PYTHONPATH=src python3 benchmarks/hostile_probe.py            # markdown table
    PYTHONPATH=src python3 benchmarks/hostile_probe.py --json probe.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import rmijax  # noqa: E402
from rmijax.robots.model import RobotModel  # noqa: E402


def _short(duration=0.3, paths=("hold", "sine")):
    return rmijax.trajectory(list(paths), duration=duration)


def _pend():
    return rmijax.paper_pendulum(), rmijax.trajectory("sine", duration=0.3)


def _arm2():
    return rmijax.paper_arm2(), _short()


def _user_model(mass=None, bias=None, fd=None):
    good_mass = lambda q, th: jnp.array([[th[0], 0.1], [0.1, th[1]]]) + 0.0 * q[0]  # noqa: E731
    good_bias = lambda q, qd, th: 9.81 * jnp.cos(q) * th  # noqa: E731
    model = RobotModel(2, 2, mass or good_mass, bias or good_bias, forward_dynamics=fd)
    return rmijax.uncertain_robot(model, [1.0, 1.0], [0.9, 0.9], [1.1, 1.1])


def _wrapped(params, traj):
    big = jax.jit(lambda t: rmijax.rmi_step(traj, params, t).upper)(np.int64(2**32 + 3))
    wrapped = rmijax.rmi_step(traj, params, 3).upper
    last = rmijax.rmi_step(traj, params, traj.n_steps).upper
    if np.allclose(big, wrapped, rtol=1e-12, atol=0) and not np.allclose(
        big, last, rtol=1e-12, atol=0
    ):
        return "answered step 3 (wrapped around)"
    if np.allclose(big, last, rtol=1e-12, atol=0):
        return f"clipped to the last step T = {traj.n_steps} (documented), no wrap"
    return "answered something else"


def _monitor_nan_desired(jitted):
    params, traj = _arm2()
    mon = rmijax.monitor(params, window=5)
    step = jax.jit(mon.update) if jitted else mon.update
    state = mon.init(traj.q_d[0], traj.qd_d[0])
    outs = []
    for k in range(20):
        q_d = traj.q_d[k].at[0].set(jnp.nan) if k == 3 else traj.q_d[k]
        state, out = step(state, (q_d, traj.qd_d[k], traj.qdd_d[k]), traj.x_n[k])
        outs.append(out)
    alarms = [int(o.alarm.any()) for o in outs]
    flag = [int(getattr(o, "desired_invalid", np.zeros(())).any()) for o in outs]
    return f"alarm per tick {''.join(map(str, alarms))}, desired_invalid {''.join(map(str, flag))}"


def _cli(*args):
    with tempfile.TemporaryDirectory() as tmp:
        argv = [a.replace("TMP", tmp) for a in args]
        if "FILE" in " ".join(argv):
            path = f"{tmp}/afile"
            open(path, "w").close()
            argv = [a.replace("FILE", path) for a in argv]
        started = time.perf_counter()
        run = subprocess.run(
            [sys.executable, "-m", "rmijax.apps.cli", *argv],
            capture_output=True,
            text=True,
            timeout=600,
        )
        took = time.perf_counter() - started
    err = run.stderr.strip().splitlines()
    tail = err[-1] if err else ""
    trace = "Traceback" in run.stderr
    return f"exit {run.returncode} in {took:.1f} s{' TRACEBACK' if trace else ''}: {tail[:110]}"


def _probes():
    pend, pend_traj = _pend()
    arm, arm_traj = _arm2()
    P = []  # (class, input, thunk)

    def add(cls, label, thunk):
        P.append((cls, label, thunk))

    # -- silently wrong under jit
    add("jit", "rmi_step(t_f=2.5) eager", lambda: rmijax.rmi_step(pend_traj, pend, 2.5))
    add(
        "jit",
        "jit(rmi_step)(t_f=2.5 float)",
        lambda: jax.jit(lambda t: rmijax.rmi_step(pend_traj, pend, t).upper)(2.5),
    )
    add("jit", "jit(rmi_step)(t_f=2**32+3 int64)", lambda: _wrapped(pend, pend_traj))
    add("jit", "rmi_step(t_f=True)", lambda: rmijax.rmi_step(pend_traj, pend, True))
    add("jit", "rmi_step(t_f=-1)", lambda: rmijax.rmi_step(pend_traj, pend, -1))
    add(
        "jit",
        "jit(rmi_step)(t_f=-1) traced",
        lambda: jax.jit(lambda t: rmijax.rmi_step(pend_traj, pend, t).upper)(-1),
    )
    # -- NaN in the desired path
    add(
        "nan",
        "trajectory_from_samples(q_d with NaN)",
        lambda: rmijax.trajectory_from_samples(
            np.r_[0.0, np.nan, 0.0][:, None], np.zeros((3, 1)), np.zeros((3, 1)), dt=0.01
        ),
    )
    add("nan", "trajectory(path -> NaN)", lambda: rmijax.trajectory(lambda t: t * jnp.nan))
    add("nan", "monitor.update(desired NaN) eager", lambda: _monitor_nan_desired(False))
    add(
        "nan", "jit(monitor.update)(desired NaN at tick 3), N=5", lambda: _monitor_nan_desired(True)
    )
    add(
        "nan",
        "monitor.init(q_d0 NaN)",
        lambda: rmijax.monitor(arm).init(jnp.array([jnp.nan, 0.0]), jnp.zeros(2)),
    )
    # -- user models
    add(
        "model",
        "singular M (rank 1)",
        lambda: rmijax.rmi(
            arm_traj, _user_model(mass=lambda q, th: jnp.ones((2, 2)) * th[0] + 0 * q[0])
        ),
    )
    add(
        "model",
        "indefinite M",
        lambda: rmijax.rmi(
            arm_traj,
            _user_model(mass=lambda q, th: jnp.diag(jnp.array([th[0], -th[1]])) + 0 * q[0]),
        ),
    )
    add(
        "model",
        "asymmetric M",
        lambda: rmijax.rmi(
            arm_traj,
            _user_model(mass=lambda q, th: jnp.array([[th[0], 0.5], [0.0, th[1]]]) + 0 * q[0]),
        ),
    )
    add(
        "model",
        "M singular only at q2 = 0.3 corner states",
        lambda: rmijax.rmi(
            arm_traj,
            _user_model(
                mass=lambda q, th: jnp.diag(jnp.array([th[0], th[1] * jnp.sin(q[1]) ** 2]))
            ),
        ),
    )
    add(
        "model",
        "h returns NaN",
        lambda: rmijax.rmi(arm_traj, _user_model(bias=lambda q, qd, th: q * jnp.nan)),
    )
    add(
        "model",
        "wrong forward_dynamics",
        lambda: rmijax.rmi(arm_traj, _user_model(fd=lambda q, qd, tau, th: tau)),
    )
    add(
        "model",
        "M of wrong shape (3, 3)",
        lambda: rmijax.rmi(arm_traj, _user_model(mass=lambda q, th: jnp.eye(3) * th[0])),
    )
    add(
        "model",
        "wrong forward_dynamics via bounds(method='linearized')",
        lambda: rmijax.bounds(
            arm_traj, _user_model(fd=lambda q, qd, tau, th: tau), method="linearized"
        ),
    )
    # -- faults
    F = rmijax.Fault
    th = arm.nominal
    add(
        "fault",
        "two faults on joint 0 encoder (bias, drift)",
        lambda: rmijax.simulate(
            arm_traj, arm, th, faults=[F("bias", 0, 0.1, value=0.1), F("drift", 0, 0.2, value=1.0)]
        ),
    )
    add(
        "fault",
        "stuck_encoder twice on joint 1",
        lambda: rmijax.simulate(
            arm_traj, arm, th, faults=[F("stuck_encoder", 1, 0.1), F("stuck_encoder", 1, 0.2)]
        ),
    )
    add(
        "fault",
        "locked and free_swinging on joint 0",
        lambda: rmijax.simulate(
            arm_traj, arm, th, faults=[F("locked", 0, 0.1), F("free_swinging", 0, 0.2)]
        ),
    )
    add("fault", "Fault('stuck_encoder', sensor=1)", lambda: F("stuck_encoder", 0, 1.0, sensor=1))
    add("fault", "Fault('locked', value=0.5)", lambda: F("locked", 0, 1.0, value=0.5))
    add("fault", "Fault('bias', joint=True)", lambda: F("bias", True, 1.0, value=0.1))
    add("fault", "Fault('bias', joint=0.0)", lambda: F("bias", 0.0, 1.0, value=0.1))
    add("fault", "Fault('bias', onset='1')", lambda: F("bias", 0, "1", value=0.1))
    add("fault", "Fault('bias', sensor=True)", lambda: F("bias", 0, 1.0, value=0.1, sensor=True))
    add(
        "fault",
        "simulate(faults=Fault onset -0.1)",
        lambda: rmijax.simulate(arm_traj, arm, th, faults=[F("locked", 0, -0.1)]),
    )
    # -- constructors and options
    add("coerce", "preset_arm(2.7)", lambda: rmijax.preset_arm(2.7))
    add("coerce", "preset_arm('3')", lambda: rmijax.preset_arm("3"))
    add("coerce", "preset_arm(True)", lambda: rmijax.preset_arm(True))
    add("coerce", "planar_arm_model(2.5)", lambda: rmijax.planar_arm_model(2.5))
    good_m = lambda q, th: jnp.eye(1) * th[0]  # noqa: E731
    good_h = lambda q, qd, th: jnp.zeros(1)  # noqa: E731
    add("coerce", "RobotModel(n_joints=1.5)", lambda: RobotModel(1.5, 1, good_m, good_h))
    add("coerce", "RobotModel(n_params='2')", lambda: RobotModel(1, "2", good_m, good_h))
    add("coerce", "RobotModel(mass_matrix=None)", lambda: RobotModel(1, 1, None, good_h))
    add("coerce", "RobotModel(bias=3.0)", lambda: RobotModel(1, 1, good_m, 3.0))
    add(
        "coerce",
        "RobotModel(forward_dynamics='fast')",
        lambda: RobotModel(1, 1, good_m, good_h, forward_dynamics="fast"),
    )
    add(
        "coerce",
        "RobotModel(param_names='ab') for p=2",
        lambda: RobotModel(1, 2, good_m, good_h, param_names="ab"),
    )
    add(
        "coerce",
        "uncertain_robot(model='arm')",
        lambda: rmijax.uncertain_robot("arm", [1.0], [1.0], [1.0]),
    )
    add(
        "coerce",
        "planar_arm(nominal=['a','b'])",
        lambda: rmijax.planar_arm(["a", "b"], [1, 1], [1, 1]),
    )
    add("coerce", "rmi(chunk_size=2.5)", lambda: rmijax.rmi(pend_traj, pend, chunk_size=2.5))
    add("coerce", "rmi(chunk_size=True)", lambda: rmijax.rmi(pend_traj, pend, chunk_size=True))
    add(
        "coerce",
        "rmi(memory_budget='4GB')",
        lambda: rmijax.rmi(pend_traj, pend, memory_budget="4GB"),
    )
    add(
        "coerce",
        "rmi(memory_budget=-1)",
        lambda: rmijax.rmi(pend_traj, pend, memory_budget=-1),
    )
    add("coerce", "rmi(progress='yes')", lambda: rmijax.rmi(pend_traj, pend, progress="yes"))
    add("coerce", "rmi(window=2.0)", lambda: rmijax.rmi(pend_traj, pend, window=2.0))
    add("coerce", "rmi(noise_hi='a')", lambda: rmijax.rmi(pend_traj, pend, noise_hi="a"))
    add(
        "coerce",
        "bounds(method='linearized', margin=-0.1)",
        lambda: rmijax.bounds(pend_traj, pend, method="linearized", margin=-0.1),
    )
    add(
        "coerce",
        "bounds(method='linearized', chunk_size=2.5)",
        lambda: rmijax.bounds(pend_traj, pend, method="linearized", chunk_size=2.5),
    )
    add(
        "coerce",
        "bounds(method='constant_corners', chunk_size=2.5)",
        lambda: rmijax.bounds(pend_traj, pend, method="constant_corners", chunk_size=2.5),
    )
    add(
        "coerce",
        "bounds(method='empirical', runs=2.5)",
        lambda: rmijax.bounds(pend_traj, pend, method="empirical", runs=2.5),
    )
    add(
        "coerce",
        "bounds(method='empirical', seed=-1)",
        lambda: rmijax.bounds(pend_traj, pend, method="empirical", seed=-1),
    )
    add(
        "coerce",
        "bounds(method='corner_search', max_rounds=1.5)",
        lambda: rmijax.bounds(pend_traj, pend, method="corner_search", max_rounds=1.5),
    )
    add(
        "coerce",
        "simulate(divergence_limit=nan)",
        lambda: rmijax.simulate(pend_traj, pend, pend.nominal, divergence_limit=float("nan")),
    )
    add(
        "coerce",
        "simulate(seed=1.5)",
        lambda: rmijax.simulate(pend_traj, pend, pend.nominal, seed=1.5),
    )
    add(
        "coerce",
        "simulate(th_true='x')",
        lambda: rmijax.simulate(pend_traj, pend, "x"),
    )
    add("coerce", "trajectory(duration=nan)", lambda: rmijax.trajectory("sine", duration=np.nan))
    add("coerce", "trajectory(duration='15')", lambda: rmijax.trajectory("sine", duration="15"))
    add("coerce", "trajectory(dt='0.01')", lambda: rmijax.trajectory("sine", dt="0.01"))
    add("coerce", "trajectory(kp='100')", lambda: rmijax.trajectory("sine", kp="100"))
    add(
        "coerce",
        "trajectory(dtype=jnp.int32)",
        lambda: rmijax.trajectory("sine", dtype=jnp.int32, duration=0.2),
    )
    add("coerce", "trajectory(paths=[])", lambda: rmijax.trajectory([]))
    add(
        "coerce",
        "trajectory_from_samples(dt=nan)",
        lambda: rmijax.trajectory_from_samples(
            np.zeros((3, 1)), np.zeros((3, 1)), np.zeros((3, 1)), dt=np.nan
        ),
    )
    bounds = rmijax.rmi(pend_traj, pend)
    y = np.asarray(bounds.nominal)
    add("coerce", "detect(dt=-0.01)", lambda: rmijax.detect(y, bounds, dt=-0.01))
    add("coerce", "detect(onset=nan)", lambda: rmijax.detect(y, bounds, onset=np.nan))
    add("coerce", "detect(persistence=2.5)", lambda: rmijax.detect(y, bounds, persistence=2.5))
    add("coerce", "detect(tol=-1)", lambda: rmijax.detect(y, bounds, tol=-1))
    add("coerce", "detect(bounds='b')", lambda: rmijax.detect(y, "b"))
    add("coerce", "monitor(dt=-0.01)", lambda: rmijax.monitor(pend, dt=-0.01))
    add("coerce", "monitor(persistence=0)", lambda: rmijax.monitor(pend, persistence=0))
    add("coerce", "monitor(kp=nan)", lambda: rmijax.monitor(pend, kp=np.nan))
    add("coerce", "containment(tol=nan)", lambda: rmijax.containment(y, bounds, tol=np.nan))
    add(
        "coerce",
        "empirical_thresholds(safety=-1)",
        lambda: rmijax.empirical_thresholds(pend_traj, pend, safety=-1),
    )
    add(
        "coerce",
        "monte_carlo_parameters(draws=-3)",
        lambda: rmijax.monte_carlo_parameters(pend, -3),
    )
    # -- cost
    half_certain = rmijax.planar_arm(
        [12.0, 10.0, 1.5, 1.0], [11.0, 10.0, 1.5, 1.0], [13.0, 10.0, 1.5, 1.0]
    )
    add(
        "cost",
        "estimate_memory(box with 3 of 4 certain, enumerate) vs all uncertain",
        lambda: (
            rmijax.estimate_memory(half_certain, search="enumerate"),
            rmijax.estimate_memory(arm, search="enumerate"),
        ),
    )
    big = rmijax.preset_arm(12)
    traj12 = rmijax.trajectory(["hold"] * 12, duration=15.0)
    six = rmijax.preset_arm(6)
    traj6 = rmijax.trajectory(["hold"] * 6, duration=15.0)

    def timed(fn):
        def run():
            started = time.perf_counter()
            try:
                fn()
            except Exception as err:
                took = time.perf_counter() - started
                raise type(err)(f"[{took:.2f} s] {err}") from err
            return f"ran in {time.perf_counter() - started:.1f} s"

        return run

    cost = [
        (
            "bounds(12-link, method='constant_corners')",
            lambda: rmijax.bounds(traj12, big, method="constant_corners"),
        ),
        ("rmi(12-link, search='enumerate')", lambda: rmijax.rmi(traj12, big, search="enumerate")),
        ("rmi(6-link, search='enumerate')", lambda: rmijax.rmi(traj6, six, search="enumerate")),
        (
            "bounds(12-link, 'rmi', memory_budget=1e5)",
            lambda: rmijax.bounds(traj12, big, method="rmi", memory_budget=10**5),
        ),
        (
            "bounds(12-link, 'corner_search', memory_budget=1e5)",
            lambda: rmijax.bounds(traj12, big, method="corner_search", memory_budget=10**5),
        ),
        (
            "bounds(12-link, 'short_window', memory_budget=1e5)",
            lambda: rmijax.bounds(
                traj12, big, method="short_window", readings=traj12.x_n, memory_budget=10**5
            ),
        ),
        (
            "bounds(12-link, 'empirical', runs=100000)",
            lambda: rmijax.bounds(traj12, big, method="empirical", runs=100000),
        ),
        (
            "simulate(2-link, 2e6 parameter draws)",
            lambda: rmijax.simulate(arm_traj, arm, np.ones((2 * 10**6, 4))),
        ),
    ]
    for label, fn in cost:
        add("cost", label, timed(fn))
    add(
        "cost",
        "rmi(window=10000) on a 30-step run: median time vs window=30",
        lambda: _window_cost(pend, pend_traj),
    )
    # -- CLI
    add("cli", "--persistence 0", lambda: _cli("--persistence", "0", "--quick", "--out", "TMP/o"))
    add("cli", "--out <existing file>", lambda: _cli("--quick", "--out", "FILE"))
    add("cli", "--draws -1", lambda: _cli("--draws", "-1", "--quick", "--out", "TMP/o"))
    add("cli", "--runs 0", lambda: _cli("--runs", "0", "--quick", "--out", "TMP/o"))
    add("cli", "--safety nan", lambda: _cli("--safety", "nan", "--quick", "--out", "TMP/o"))
    add("cli", "--onset 99", lambda: _cli("--onset", "99", "--quick", "--out", "TMP/o"))
    add("cli", "--bogus", lambda: _cli("--bogus"))
    return P


def _window_cost(params, traj):
    def once(window):
        rmijax.rmi(traj, params, window=window).upper.block_until_ready()
        times = []
        for _ in range(7):
            started = time.perf_counter()
            b = rmijax.rmi(traj, params, window=window)
            b.upper.block_until_ready()
            times.append(time.perf_counter() - started)
        return float(np.median(times)), b

    long_t, long_b = once(10000)
    short_t, short_b = once(traj.n_steps)
    same = bool(np.array_equal(np.asarray(long_b.upper), np.asarray(short_b.upper)))
    return f"{long_t * 1e3:.1f} ms vs {short_t * 1e3:.1f} ms, same bounds: {same}"


def _answer(thunk):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            value = thunk()
        except SystemExit as err:
            return "refused", f"SystemExit {err.code}"
        except Exception as err:  # noqa: BLE001 - a probe records every answer
            first = str(err).strip().splitlines()[0] if str(err).strip() else ""
            return "refused", f"{type(err).__name__}: {first[:160]}"
    note = f" (warned: {str(caught[0].message)[:80]})" if caught else ""
    if isinstance(value, str):
        return "answered", value + note
    if isinstance(value, rmijax.Bounds):
        return "accepted", f"Bounds {tuple(value.upper.shape)}{note}"
    text = repr(value)
    return "accepted", (text if len(text) < 100 else type(value).__name__) + note


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", help="also write the rows to this JSON file")
    parser.add_argument("--only", help="run only probes of this class (jit, nan, model, ...)")
    args = parser.parse_args(argv)
    rows = []
    print("| class | input | answer now |")
    print("|---|---|---|")
    for cls, label, thunk in _probes():
        if args.only and cls != args.only:
            continue
        verdict, detail = _answer(thunk)
        rows.append(dict(cls=cls, input=label, verdict=verdict, detail=detail))
        print(f"| {cls} | `{label}` | {verdict}: {detail.replace('|', '/')} |", flush=True)
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(rows, handle, indent=1)


if __name__ == "__main__":
    main()
