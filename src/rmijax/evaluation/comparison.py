"""A fair comparison of bound methods on the same robot, motion and faults.

Every method's bands (:func:`rmijax.bounds`) are scored on one *case* (a robot, a
desired motion and the true robot of the fault runs):

- tightness: band width over the worst-case range that :func:`rmijax.worst_case_table`
  finds at a few times (an inner estimate of what the true plant reaches);
- safety: containment of Monte-Carlo runs of the fault-free true plant (all corners
  where ``K`` allows, plus uniform draws) and of the worst-case points;
- detection: latency and false alarms over a fault suite (every kind, every joint,
  several onsets), and false alarms on the fault-free run;
- cost: seconds per end step of the offline computation (after compilation); for a
  method that only computes whole runs (:data:`WHOLE_RUN_METHODS`), the whole run's
  seconds divided by its number of steps, recorded as such.

A method that refuses a case (:class:`~rmijax.methods.base.DivergedError`, or
``NotImplementedError`` for a model it does not support) is reported as diverged or
not supported, not scored and not dropped.

``benchmarks/methods.py`` runs it over several cases and writes JSON;
``notebooks/method_comparison.ipynb`` shows the tables and figures.
"""

from __future__ import annotations

import dataclasses
import time

import jax
import numpy as np

from rmijax.detection.detect import containment, detect
from rmijax.detection.suite import default_fault_suite
from rmijax.evaluation.worst_case import worst_case_table
from rmijax.methods.base import DivergedError
from rmijax.methods.dispatch import bounds
from rmijax.plant import simulate
from rmijax.robots.box import UncertainRobot, monte_carlo_parameters
from rmijax.trajectory import Trajectory

__all__ = ["WHOLE_RUN_METHODS", "Case", "compare", "prefix", "step_cost", "summary_rows"]

_CORNER_LIMIT = 4096
"""Monte-Carlo runs include every corner when ``K`` is at most this."""

WHOLE_RUN_METHODS = ("certified",)
"""Methods that compute a whole run at once (no end step of their own to time).

Their bands are causal (the first ``k`` steps of a run's band are the band of the
run's first ``k`` steps), so a divergence found on a prefix is the whole run's.
"""


@dataclasses.dataclass(frozen=True)
class Case:
    """One comparison case.

    Attributes:
        name: a label.
        params: the robot and its box.
        traj: the desired motion.
        th_true: (p,) the true robot of the fault runs.
    """

    name: str
    params: UncertainRobot
    traj: Trajectory
    th_true: np.ndarray


class _Containment:
    """:func:`rmijax.containment` accumulated over chunks of runs (SPEC section 7)."""

    def __init__(self):
        self.samples = self.inside = self.runs = self.clean = 0
        self.worst = 0.0

    def add(self, states, band, tol=1e-9):
        part = containment(states, band, tol=tol)
        x = np.asarray(states)
        self.samples += x.size
        self.inside += round(part["inside"] * x.size)
        self.runs += part["runs"]
        self.clean += round(part["clean_runs"] * part["runs"])
        self.worst = max(self.worst, part["worst"])

    def result(self):
        return {
            "inside": self.inside / max(self.samples, 1),
            "clean_runs": self.clean / max(self.runs, 1),
            "worst": self.worst,
            "runs": self.runs,
        }


def _held(readings):
    """Readings with NaN samples (a diverged faulty run) replaced by the last finite one.

    Only used to build ``short_window`` bands; the detector still sees the NaN,
    which always alarms.
    """
    y = np.array(readings, np.float64)
    for k in range(1, y.shape[0]):
        bad = ~np.isfinite(y[k])
        y[k][bad] = y[k - 1][bad]
    return y


def prefix(traj: Trajectory, steps: int) -> Trajectory:
    """The first ``steps`` steps of ``traj`` (``steps + 1`` samples), same gains and step."""
    steps = int(steps)
    if not 1 <= steps <= traj.n_steps:
        raise ValueError(f"steps must be in [1, {traj.n_steps}], got {steps}")
    arrays = {
        f.name: getattr(traj, f.name)[: steps + 1]
        for f in dataclasses.fields(traj)
        if f.name in ("t", "q_d", "qd_d", "qdd_d", "u_d", "x_n", "qdd_n")
    }
    return dataclasses.replace(traj, **arrays)


def _timed_bounds(case, method, readings, options, timing_steps, probe_steps, warm=True):
    """Bounds of ``method`` over the whole run, and how its cost was measured.

    Windowed methods: the second of two calls on the first ``timing_steps`` steps
    (the first compiles), divided by the ``timing_steps + 1`` end steps. Methods of
    :data:`WHOLE_RUN_METHODS`: first run on the first ``probe_steps`` steps (a
    divergence there is the whole run's, found for a fraction of its cost), then
    two calls on the whole run; the second, divided by the run's ``T`` steps. With
    ``warm=False`` a whole-run method is called once (a long certified run costs half):
    its cost is that call's seconds, compilation included, over ``T``.

    Returns:
        ``(band, cost)`` with ``cost`` a dict: ``seconds_per_step``, ``cost_basis``
        (``"end_step"``, ``"whole_run"`` or, with ``warm=False``, ``"whole_run_cold"``),
        and for whole runs ``whole_run_first_s`` (the first call, with compilation) and,
        when warm, ``whole_run_s`` (the second).

    Raises:
        DivergedError: the method's bands diverged (on the probe, the message says so).
        NotImplementedError: the method does not support the case's model.
    """
    kwargs = dict(options)
    if method in WHOLE_RUN_METHODS:
        if probe_steps and probe_steps < case.traj.n_steps:
            try:
                bounds(prefix(case.traj, probe_steps), case.params, method=method, **kwargs)
            except DivergedError as err:
                raise DivergedError(
                    f"{err} [found on the first {int(probe_steps)} of {case.traj.n_steps} "
                    "steps; the band is causal, so the whole run diverges there too]",
                    step=err.step,
                    joint=err.joint,
                    sensor=err.sensor,
                ) from err
        seconds = []
        for _ in range(2 if warm else 1):
            start = time.perf_counter()
            band = bounds(case.traj, case.params, method=method, **kwargs)
            jax.block_until_ready(band.upper)
            seconds.append(time.perf_counter() - start)
        return band, {
            "seconds_per_step": seconds[-1] / case.traj.n_steps,
            "cost_basis": "whole_run" if warm else "whole_run_cold",
            **({"whole_run_s": seconds[-1]} if warm else {}),
            "whole_run_first_s": seconds[0],
        }
    if method == "short_window":
        kwargs["readings"] = readings
    band = bounds(case.traj, case.params, method=method, **kwargs)
    jax.block_until_ready(band.upper)
    steps = min(int(timing_steps), case.traj.n_steps)
    short = prefix(case.traj, steps)
    if method == "short_window":
        kwargs["readings"] = np.asarray(readings)[: steps + 1]
    seconds = []
    for _ in range(2):
        start = time.perf_counter()
        jax.block_until_ready(bounds(short, case.params, method=method, **kwargs).upper)
        seconds.append(time.perf_counter() - start)
    return band, {"seconds_per_step": seconds[-1] / (steps + 1), "cost_basis": "end_step"}


def step_cost(case: Case, method: str, *, end_steps=(1,), window=100, **options) -> dict:
    """Seconds of one online end step of ``rmi`` or ``corner_search`` (compiled, window full).

    For the sizes where a whole run is out of reach. Returns ``{"compile_s",
    "step_s", "calls"}``: compile plus first call, then the median of the
    calls at ``end_steps`` (each ``>= window`` is a full window).
    """
    from rmijax.methods.corner_search import corner_search_step
    from rmijax.methods.rmi import rmi_step

    one = {"rmi": rmi_step, "corner_search": corner_search_step}[method]
    traj, params = case.traj, case.params
    fn = jax.jit(lambda t: one(traj, params, t, window=window, **options).upper)
    start = time.perf_counter()
    jax.block_until_ready(fn(int(end_steps[0])))
    compile_s = time.perf_counter() - start
    times = []
    for t_f in end_steps:
        start = time.perf_counter()
        jax.block_until_ready(fn(int(t_f)))
        times.append(time.perf_counter() - start)
    return {"compile_s": compile_s, "step_s": float(np.median(times)), "calls": len(times)}


def _tightness(band, table, times, dt, tol=1e-9):
    """Band width over the worst-case range, and containment of the worst-case points."""
    steps = np.rint(np.asarray(times) / dt).astype(int)
    lower = np.asarray(band.lower, np.float64)[steps]
    upper = np.asarray(band.upper, np.float64)[steps]
    low, high = np.asarray(table["low"]), np.asarray(table["high"])
    spread = high - low
    ratio = np.where(spread > 0, (upper - lower) / np.where(spread > 0, spread, 1.0), np.nan)
    contained = np.concatenate([(low >= lower - tol).ravel(), (high <= upper + tol).ravel()])
    per_sensor = {}
    for s, sensor in enumerate(("encoder", "tachometer")):
        values = ratio[..., s][np.isfinite(ratio[..., s])]
        per_sensor[sensor] = {
            "median": float(np.median(values)) if values.size else float("nan"),
            "min": float(values.min()) if values.size else float("nan"),
            "max": float(values.max()) if values.size else float("nan"),
        }
    return {"width_over_worst": per_sensor, "worst_points_inside": float(contained.mean())}


def _extreme_rows(states, th, steps, into):
    """Add to ``into`` (a dict row-bytes -> row) the parameter rows of the highest and
    lowest Monte-Carlo value of every output at ``steps``."""
    x = np.asarray(states, np.float64)[:, steps]  # (R, S, n, 2)
    x = np.where(np.isfinite(x), x, np.nan)
    for pick in (np.nanargmax, np.nanargmin):
        for r in np.unique(pick(x, axis=0)):
            row = np.asarray(th[r], np.float64)
            into.setdefault(row.tobytes(), row)


def compare(
    case: Case,
    methods,
    *,
    options=None,
    onsets=(3.0, 7.0),
    draws=1000,
    times=None,
    short_window_runs=20,
    worst_options=None,
    max_worst_starts=16,
    timing_steps=200,
    probe_steps=50,
    warm=True,
    seed=0,
    chunk=256,
    log=print,
):
    """Score each method of ``methods`` on ``case``; a JSON-ready dict.

    Args:
        case: the robot, motion and true robot.
        methods: names accepted by :func:`rmijax.bounds`.
        options: ``{method: {option: value}}`` passed to :func:`rmijax.bounds`.
        onsets: fault onsets in s; each fault kind on each joint at each onset.
        draws: uniform Monte-Carlo draws (plus every corner if ``K <= 4096``).
        times: times (s) of the worst-case search; default 8 spread over the run.
        short_window_runs: how many Monte-Carlo runs score ``short_window``
            (its bands are rebuilt from every run's readings).
        worst_options: passed to :func:`rmijax.worst_case_table`.
        max_worst_starts: the Monte-Carlo runs' extreme parameter rows at
            ``times`` (the constant-corner envelope's corners among them) start
            the worst-case search: the first this many distinct rows found
            (in the order of the runs, so corners before uniform draws).
        timing_steps: the cost is timed on the first this many steps.
        probe_steps: methods of :data:`WHOLE_RUN_METHODS` are first run on this
            many steps, so that a divergence costs a prefix, not a whole run
            (None or 0: no probe).
        warm: time whole-run methods by a second, compiled call (True) or by their
            only call, compilation included (False: half the cost of a long run).
        seed: seeds the draws.
        chunk: Monte-Carlo runs simulated at once.
        log: a callable taking progress messages, or None.

    Returns:
        ``{"case", "n", "K", "T", "dt", "methods": {name: {...}}, "worst_case": {...},
        "faults": [...], "diverged": {name: message}, "not_supported": {name:
        message}}`` (a method that raised :class:`~rmijax.methods.base.DivergedError`
        or ``NotImplementedError`` is reported there and not scored; when no method
        is left, nothing is simulated and ``worst_case`` is None and ``faults`` empty);
        ``methods[name]`` has ``seconds_per_step``, ``cost_basis`` (``"end_step"``, or
        ``"whole_run"`` with ``whole_run_s`` and ``whole_run_first_s``: the run's
        seconds warm and with compilation, ``seconds_per_step`` being the warm one over
        ``T``; or ``"whole_run_cold"`` with ``whole_run_first_s`` only, when
        ``warm=False``),
        ``width_over_worst`` (per sensor: median, min, max of band width over
        worst-case range), ``worst_points_inside``, ``containment`` (``inside``,
        ``clean_runs``, ``worst``, ``runs``), ``detected``, ``median_latency``,
        ``false_alarms_fault_runs``, ``false_alarms_fault_free``, ``mean_width``.
    """
    log = log or (lambda *_: None)
    options = options or {}
    traj, params = case.traj, case.params
    n, duration = params.n_joints, traj.n_steps * traj.dt
    if times is None:
        times = np.round(np.linspace(0.1 * duration, 0.95 * duration, 8) / traj.dt) * traj.dt
    steps = np.rint(np.asarray(times) / traj.dt).astype(int)
    _, y_free = simulate(traj, params, case.th_true)
    result = {
        "case": case.name,
        "n": n,
        "K": params.n_corners,
        "T": traj.n_steps,
        "dt": traj.dt,
        "methods": {},
    }

    log(f"[{case.name}] bands")
    bands, cost, diverged, unsupported = {}, {}, {}, {}
    for method in methods:
        started = time.perf_counter()
        try:
            bands[method], cost[method] = _timed_bounds(
                case, method, y_free, options.get(method, {}), timing_steps, probe_steps, warm
            )
        except DivergedError as err:  # the method refuses this case: say so, score the rest
            diverged[method] = str(err)
            log(f"  {method}: diverged ({err})")
            continue
        except NotImplementedError as err:  # e.g. certified on a model it cannot evaluate
            unsupported[method] = str(err)
            log(f"  {method}: not supported ({err})")
            continue
        basis = cost[method]["cost_basis"]
        per = "end step" if basis == "end_step" else f"step ({_BASIS[basis]})"
        log(
            f"  {method}: {cost[method]['seconds_per_step'] * 1e3:.3f} ms per {per} "
            f"({time.perf_counter() - started:.1f} s with the timing)"
        )

    methods = [m for m in methods if m in bands]
    result["diverged"] = diverged
    result["not_supported"] = unsupported
    if not methods:  # nothing to score: no Monte-Carlo runs, worst case or faults
        result.update(worst_case=None, faults=[])
        return result

    log(f"[{case.name}] Monte-Carlo containment")
    th = monte_carlo_parameters(params, draws, seed=seed, corners=params.n_corners <= _CORNER_LIMIT)
    counts = {m: _Containment() for m in methods}
    extremes = {}
    for first in range(0, th.shape[0], chunk):
        states, _ = simulate(traj, params, th[first : first + chunk])
        _extreme_rows(states, th[first : first + chunk], steps, extremes)
        for method in methods:
            if method != "short_window":
                counts[method].add(states, bands[method])
        if "short_window" in methods and first < short_window_runs:
            for run in np.asarray(states)[: max(0, short_window_runs - first)]:
                band = bounds(
                    traj,
                    params,
                    method="short_window",
                    readings=run,
                    **options.get("short_window", {}),
                )
                counts["short_window"].add(run[None], band)

    log(f"[{case.name}] worst case at {len(times)} times")
    rows = list(extremes.values())
    rows = np.stack(rows[:max_worst_starts]) if rows else None
    started = time.perf_counter()
    table = worst_case_table(traj, params, times, starts=rows, seed=seed, **(worst_options or {}))
    result["worst_case"] = {
        "times": [float(t) for t in times],
        "low": np.asarray(table["low"]).tolist(),
        "high": np.asarray(table["high"]).tolist(),
        "seconds": time.perf_counter() - started,
        "starts": 0 if rows is None else int(rows.shape[0]),
    }

    log(f"[{case.name}] fault suite")
    faults = [f for onset in onsets for f in default_fault_suite(n, onset)]
    fault_rows = []
    for fault in faults:
        x_true, y_meas = simulate(traj, params, case.th_true, faults=[fault])
        row = {"fault": fault.label, "kind": fault.kind, "joint": fault.joint, "onset": fault.onset}
        for method in methods:
            band = bands[method]
            if method == "short_window":
                band = bounds(
                    traj,
                    params,
                    method="short_window",
                    readings=_held(y_meas),
                    **options.get("short_window", {}),
                )
            found = detect(y_meas, band, onset=fault.onset, x_true=x_true)
            row[method] = {"latency": found.latency, "false_alarms": found.false_alarms}
        fault_rows.append(row)
    result["faults"] = fault_rows

    for method in methods:
        latencies = [r[method]["latency"] for r in fault_rows]
        detected = [v for v in latencies if v is not None]
        free = detect(y_free, bands[method])
        result["methods"][method] = {
            **cost[method],
            **_tightness(bands[method], table, times, traj.dt),
            "containment": counts[method].result(),
            "detected": len(detected) / max(len(fault_rows), 1),
            "median_latency": float(np.median(detected)) if detected else None,
            "false_alarms_fault_runs": int(sum(r[method]["false_alarms"] for r in fault_rows)),
            "false_alarms_fault_free": int(free.false_alarms),
            "mean_width": np.asarray(bands[method].width).mean(axis=(0, 1)).tolist(),
        }
    return result


def summary_rows(results):
    """One flat row per (case, method) of :func:`compare` results, for tables.

    ``status`` is ``"scored"``, ``"diverged"`` or ``"not supported"`` (a refused
    method's row has NaN scores); ``cost_basis`` says what ``ms_per_step`` divides:
    ``"end step"`` (one end step timed), ``"whole run / T"`` (a warm whole run's
    seconds over its ``T`` steps) or ``"cold whole run / T"`` (the only call's,
    compilation included: ``compare(..., warm=False)``).
    """
    nan = float("nan")
    rows = []
    for result in results:
        for method, m in result["methods"].items():
            basis = _BASIS[m.get("cost_basis", "end_step")]
            rows.append(
                {
                    "case": result["case"],
                    "n": result["n"],
                    "method": method,
                    "status": "scored",
                    "ms_per_step": m["seconds_per_step"] * 1e3,
                    "cost_basis": basis,
                    "enc_width_over_worst": m["width_over_worst"]["encoder"]["median"],
                    "tach_width_over_worst": m["width_over_worst"]["tachometer"]["median"],
                    "worst_points_inside": m["worst_points_inside"],
                    "mc_inside": m["containment"]["inside"],
                    "mc_clean_runs": m["containment"]["clean_runs"],
                    "mc_worst": m["containment"]["worst"],
                    "detected": m["detected"],
                    "median_latency": nan if m["median_latency"] is None else m["median_latency"],
                    "false_alarms_free": m["false_alarms_fault_free"],
                    "false_alarms_faulty": m["false_alarms_fault_runs"],
                }
            )
        refused = [(m, "diverged") for m in result.get("diverged", {})]
        refused += [(m, "not supported") for m in result.get("not_supported", {})]
        for method, status in refused:
            rows.append(
                {
                    "case": result["case"],
                    "n": result["n"],
                    "method": method,
                    "status": status,
                    "cost_basis": "-",
                    **dict.fromkeys(_SCORES, nan),
                }
            )
    return rows


_BASIS = {
    "end_step": "end step",
    "whole_run": "whole run / T",
    "whole_run_cold": "cold whole run / T",
}

_SCORES = (
    "ms_per_step",
    "enc_width_over_worst",
    "tach_width_over_worst",
    "worst_points_inside",
    "mc_inside",
    "mc_clean_runs",
    "mc_worst",
    "detected",
    "median_latency",
    "false_alarms_free",
    "false_alarms_faulty",
)
"""The numeric columns of :func:`summary_rows` (NaN in a refused method's row)."""
