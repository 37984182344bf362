"""The main job for a real arm: a pick-and-place move, bands, the fault suite, figures, report.

``rmijax --robot panda --out DIR`` (also ``iiwa14``, ``ur5e``, or a URDF/MJCF
path) loads the arm with its default uncertain box
(:func:`~rmijax.robots.loaders.default_box`: every link mass +-10 %, a payload of
0-1 kg at the flange, viscous and Coulomb friction on every joint, scaled to the
joint's inertia), moves it
through a pick-and-place-like sequence of joint-space waypoints, computes the
bands of every output with each method, runs every fault kind on every joint
against a true robot inside the box, and writes figures, ``report.json`` and
``report.md``.
"""

from __future__ import annotations

import dataclasses
import pathlib
import xml.etree.ElementTree as ET

import numpy as np

from rmijax.apps.experiments import fault_table
from rmijax.detection.detect import detect
from rmijax.detection.suite import default_fault_suite
from rmijax.methods.dispatch import bounds
from rmijax.plant import simulate
from rmijax.robots.box import UncertainRobot
from rmijax.robots.loaders import SHIPPED, default_box, description_path, load_robot
from rmijax.trajectory import Trajectory, waypoint_trajectory

__all__ = [
    "METHODS",
    "RealArmCase",
    "home_pose",
    "pick_and_place",
    "real_arm_case",
    "run",
]

METHODS = ("rmi", "linearized", "empirical")
"""Band methods the job compares by default."""

TRUE_FRACTION = 0.6
"""The true robot of the fault runs: every parameter at ``nominal + 0.6 (hi - nominal)``."""

# Joint-space offsets from the home pose (rad) of the pick-and-place sequence: approach,
# pick, lift, carry, place, lift, back home. Joints past the fourth keep their home angle
# except a wrist turn, so the move suits 6- and 7-joint arms alike.
_MOVES = (
    (0.0, 0.0, 0.0, 0.0),
    (0.45, 0.25, 0.0, 0.30),
    (0.45, 0.40, 0.0, 0.45),
    (0.45, 0.25, 0.0, 0.30),
    (-0.45, 0.25, 0.0, 0.30),
    (-0.45, 0.40, 0.0, 0.45),
    (-0.45, 0.25, 0.0, 0.30),
    (0.0, 0.0, 0.0, 0.0),
)
_WRIST = (0.0, 0.0, 0.0, 0.0, 0.5, 0.5, 0.5, 0.0)


def home_pose(source) -> np.ndarray:
    """The ``home`` keyframe of a shipped arm or MJCF file, or zeros when it has none (rad)."""
    params = load_robot(source)
    path = description_path(source)
    if path.suffix == ".xml":
        key = ET.parse(path).getroot().find(".//keyframe/key[@name='home']")
        if key is not None and key.get("qpos"):
            qpos = np.array([float(x) for x in key.get("qpos").split()])
            if qpos.size == params.n_joints:
                return qpos
    return np.zeros(params.n_joints)


def pick_and_place(home, *, segment_time: float = 1.0, dt: float = 0.01, kp=100.0, kd=20.0):
    """A pick-and-place-like move through joint-space waypoints around ``home`` (rad).

    Eight waypoints (home, approach, pick, lift, carry, place, lift, home), a
    rest-to-rest minimum-jerk segment of ``segment_time`` s between each, with
    the default critically damped gains.

    Returns:
        A :class:`~rmijax.trajectory.Trajectory` of ``7 segment_time`` s.
    """
    home = np.asarray(home, np.float64)
    points = np.repeat(home[None], len(_MOVES), axis=0)
    for k, (move, wrist) in enumerate(zip(_MOVES, _WRIST, strict=True)):
        points[k, : min(4, home.size)] += np.asarray(move[: min(4, home.size)])
        if home.size > 4:
            points[k, -1] += wrist
    return waypoint_trajectory(points, segment_time=segment_time, dt=dt, kp=kp, kd=kd)


@dataclasses.dataclass(frozen=True)
class RealArmCase:
    """The arm, its box, the move and the true robot of the job."""

    name: str
    params: UncertainRobot
    traj: Trajectory
    th_true: np.ndarray


def real_arm_case(source="panda", *, segment_time=1.0, box=None) -> RealArmCase:
    """The job's case for ``source`` (a shipped name or a URDF/MJCF path).

    ``box``: keyword arguments of :func:`~rmijax.robots.loaders.load_robot`; default
    :func:`~rmijax.robots.loaders.default_box` of ``source``."""
    params = load_robot(source, **(default_box(source) if box is None else box))
    traj = pick_and_place(home_pose(source), segment_time=segment_time)
    nominal, hi = np.asarray(params.nominal), np.asarray(params.hi)
    th_true = nominal + TRUE_FRACTION * (hi - nominal)
    name = source if isinstance(source, str) and source in SHIPPED else pathlib.Path(source).stem
    return RealArmCase(name, params, traj, th_true)


def _method_bounds(case, method, readings):
    if method == "short_window":
        return bounds(case.traj, case.params, method=method, readings=readings)
    return bounds(case.traj, case.params, method=method)


def run(
    source, out, *, methods=METHODS, segment_time=1.0, onset=None, persistence=1, progress=True
):
    """Run the job and write figures, ``report.json`` and ``report.md`` to ``out``.

    Args:
        source: a shipped arm name or a URDF/MJCF path.
        out: output folder (created).
        methods: band methods to compare (names of :data:`rmijax.METHODS`).
        segment_time: s per waypoint segment (the move lasts 7 segments).
        onset: fault onset in s; default the middle of the move.
        persistence: consecutive out-of-band steps for an alarm.
        progress: show progress bars.

    Returns:
        The report as a dict.
    """
    import json
    import time

    from tqdm.auto import tqdm

    from rmijax.apps.plotting import plot_bands, save_figure

    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    case = real_arm_case(source, segment_time=segment_time)
    traj, params = case.traj, case.params
    duration = float(traj.t[-1])
    onset = 0.5 * duration if onset is None else float(onset)
    x_free, y_free = simulate(traj, params, case.th_true)
    report = {
        "robot": case.name,
        "settings": {
            "param_names": list(params.model.param_names),
            "nominal": np.asarray(params.nominal).tolist(),
            "lo": np.asarray(params.lo).tolist(),
            "hi": np.asarray(params.hi).tolist(),
            "th_true": case.th_true.tolist(),
            "duration_s": duration,
            "dt": traj.dt,
            "onset_s": onset,
            "persistence": persistence,
            "methods": list(methods),
        },
        "methods": {},
        "fault_table": [],
        "figures": [],
    }
    bands = {}
    for method in tqdm(methods, desc=f"{case.name} bands", disable=not progress):
        began = time.perf_counter()
        band = _method_bounds(case, method, y_free)
        seconds = time.perf_counter() - began
        bands[method] = band
        free = detect(y_free, band, persistence=persistence, x_true=x_free)
        width = np.asarray(band.upper - band.lower)
        report["methods"][method] = {
            "seconds": seconds,
            "false_alarms_fault_free": free.false_alarms,
            "median_width": {
                "encoder_rad": float(np.median(width[..., 0])),
                "tachometer_rad_s": float(np.median(width[..., 1])),
            },
        }
        fig = plot_bands(
            np.asarray(traj.t),
            band,
            y_meas=y_free,
            relative=True,
            title=f"{case.name}: {method} bands, fault-free true robot",
        )
        report["figures"].append(save_figure(fig, out / f"bands_{method}.png").name)
    faults = default_fault_suite(params.n_joints, onset=onset)
    bar = tqdm(total=len(faults), desc=f"{case.name} fault suite", disable=not progress)
    rows = fault_table(
        traj,
        params,
        case.th_true,
        bands,
        faults,
        persistence=persistence,
        progress=lambda done, total: bar.update(1),
    )
    bar.close()
    for row in rows:
        entry = {"kind": row.fault.kind, "joint": row.fault.joint, "results": {}}
        for method, found in row.results.items():
            entry["results"][method] = {
                "latency_s": found.latency,
                "false_alarms": found.false_alarms,
                "alarm_output": found.alarm_output,
            }
        report["fault_table"].append(entry)
    report["seconds"] = time.perf_counter() - started
    (out / "report.json").write_text(json.dumps(report, indent=2, default=_jsonable))
    (out / "report.md").write_text(_markdown(report))
    return report


def _jsonable(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, tuple | list):
        return list(value)
    return str(value)


def summary_by_kind(report) -> list[dict]:
    """Per fault kind and method: joints detected, median latency, false alarms before onset."""
    rows = []
    kinds = sorted({entry["kind"] for entry in report["fault_table"]}, key=str)
    for kind in kinds:
        entries = [e for e in report["fault_table"] if e["kind"] == kind]
        for method in report["settings"]["methods"]:
            latencies = [e["results"][method]["latency_s"] for e in entries]
            found = [x for x in latencies if x is not None]
            rows.append(
                dict(
                    kind=kind,
                    method=method,
                    detected=f"{len(found)}/{len(entries)}",
                    median_latency_s=float(np.median(found)) if found else None,
                    false_alarms=sum(e["results"][method]["false_alarms"] for e in entries),
                )
            )
    return rows


def _markdown(report) -> str:
    settings = report["settings"]
    lines = [
        f"# rmijax real-arm job: {report['robot']}",
        "",
        f"Pick-and-place move of {settings['duration_s']:g} s at dt = {settings['dt']:g} s; "
        f"faults at {settings['onset_s']:g} s, alarm after {settings['persistence']} "
        "consecutive out-of-band step(s). Parameters (nominal [lo, hi]):",
        "",
    ]
    for name, nom, lo, hi in zip(
        settings["param_names"], settings["nominal"], settings["lo"], settings["hi"], strict=True
    ):
        lines.append(f"- `{name}`: {nom:.4g} [{lo:.4g}, {hi:.4g}]")
    lines += [
        "",
        "## Bands",
        "",
        "| method | seconds | median width enc (rad) | median width tach (rad/s) "
        "| false alarms, fault-free run |",
        "|---|---|---|---|---|",
    ]
    for method, info in report["methods"].items():
        width = info["median_width"]
        lines.append(
            f"| {method} | {info['seconds']:.1f} | {width['encoder_rad']:.3g} "
            f"| {width['tachometer_rad_s']:.3g} | {info['false_alarms_fault_free']} |"
        )
    lines += [
        "",
        "## Fault suite (every kind on every joint)",
        "",
        "| fault | method | joints detected | median latency (s) | false alarms before onset |",
        "|---|---|---|---|---|",
    ]
    for row in summary_by_kind(report):
        latency = "-" if row["median_latency_s"] is None else f"{row['median_latency_s']:.2f}"
        lines.append(
            f"| {row['kind']} | {row['method']} | {row['detected']} | {latency} "
            f"| {row['false_alarms']} |"
        )
    lines += ["", "Figures: " + ", ".join(f"`{name}`" for name in report["figures"]), ""]
    return "\n".join(lines)
