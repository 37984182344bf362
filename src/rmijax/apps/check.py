"""``rmijax check``: detection reports for recorded logs, one log or a folder of them.

rmijax check run.mcap --robot paper_arm2 --out report/       # one log: report/report.md
rmijax check logs/ --robot preset3 --out reports/             # reports/<log>/report.md

For each log: ``report.json`` and ``report.md`` (first alarm, which output, how
far outside its band, alarm-free stretches, gaps, NaN readings) and
``bands.png`` (bands, readings and alarms). A folder is resumable: logs whose
``report.json`` exists are skipped (``--force`` redoes them); the bands of the
rest are computed in batches sharded across the devices (:mod:`rmijax.fleet`).
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys
import time

__all__ = ["check_log", "main"]

SENSORS = ("encoder", "tachometer")
UNITS = ("rad", "rad/s")
_SHUTDOWN_WAIT_S = 24 * 3600  # --distributed: how long a finished process waits for the rest


class _Refused(Exception):
    """An option that cannot work; one line, exit status 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise _Refused(message)


def _parser():
    from rmijax.methods.dispatch import METHODS

    parser = _Parser(
        prog="rmijax check",
        description=(
            "Detection reports for recorded robot logs (CSV, NPZ, ROS 1 .bag, ROS 2 bag "
            "folder/.db3/.mcap): bands of the robot's model along the logged reference, "
            "readings against them, alarms. LOG may be a folder of logs."
        ),
    )
    parser.add_argument("log", metavar="LOG", help="a log file or bag, or a folder of logs")
    parser.add_argument(
        "--robot",
        required=True,
        help="robot name: paper_pendulum, paper_arm2, preset<n>, or a real arm of "
        "rmijax.load_robot",
    )
    parser.add_argument("--method", default="rmi", choices=METHODS, help="band method")
    parser.add_argument("--mode", default="coupled", choices=("coupled", "per_joint"))
    parser.add_argument("--window", type=int, default=None, help="window N in steps")
    parser.add_argument("--dt", type=float, default=0.01, help="the controller's step in s")
    parser.add_argument("--kp", type=float, default=100.0, help="proportional gain, 1/s^2")
    parser.add_argument("--kd", type=float, default=20.0, help="derivative gain, 1/s")
    parser.add_argument(
        "--reading-rule", default="hold", choices=("hold", "nearest"), help="readings onto the grid"
    )
    parser.add_argument(
        "--max-gap", type=float, default=None, help="longest bridged gap in s (default 10 dt)"
    )
    parser.add_argument("--noise", type=float, default=0.0, help="sensor noise bound +-V")
    parser.add_argument("--persistence", type=int, default=1, help="consecutive steps to alarm")
    parser.add_argument("--tol", type=float, default=1e-9, help="how far outside alarms")
    parser.add_argument("--joint-state-topic", default=None, help="bags: the JointState topic")
    parser.add_argument("--reference-topic", default=None, help="bags: the reference topic")
    parser.add_argument("--out", default="rmijax-check", help="output folder (created)")
    parser.add_argument("--force", action="store_true", help="redo logs already reported")
    parser.add_argument(
        "--batch", type=int, default=None, help="logs per sharded batch (default 8 per device)"
    )
    parser.add_argument("--devices", type=int, default=None, help="use the first K devices")
    parser.add_argument(
        "--distributed",
        action="store_true",
        help="multi-host: call jax.distributed.initialize() and take this process's share "
        "of the logs (on SLURM/Open MPI/Kubernetes the three options below are detected)",
    )
    parser.add_argument("--coordinator", default=None, help="host:port of process 0")
    parser.add_argument("--num-processes", type=int, default=None, help="processes in the job")
    parser.add_argument("--process-id", type=int, default=None, help="this process, 0-based")
    parser.add_argument("--no-figures", action="store_true", help="no bands.png (faster)")
    parser.add_argument("--float32", action="store_true", help="compute in float32")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    return parser


def _validate(args):
    """Every option checked before any work; raises _Refused with one line."""
    from rmijax.io import is_bag, is_log, resolve_robot, robot_joint_names

    positive = {"--dt": args.dt, "--kp": args.kp, "--kd": args.kd}
    if args.max_gap is not None:
        positive["--max-gap"] = args.max_gap
    for name, value in positive.items():
        if not (math.isfinite(value) and value > 0):
            raise _Refused(f"{name} must be a positive number, got {value!r}")
    for name, value in {"--noise": args.noise, "--tol": args.tol}.items():
        if not (math.isfinite(value) and value >= 0):
            raise _Refused(f"{name} must be >= 0, got {value!r}")
    for name, value in {
        "--window": args.window,
        "--persistence": args.persistence,
        "--batch": args.batch,
        "--devices": args.devices,
    }.items():
        if value is not None and value < 1:
            raise _Refused(f"{name} must be >= 1, got {value!r}")
    if args.method in ("empirical", "certified") and args.window is not None:
        raise _Refused(f"--method {args.method} has no --window")
    if args.mode == "per_joint" and args.method not in ("rmi", "short_window", "corner_search"):
        raise _Refused(f"--mode per_joint does not apply to --method {args.method}")
    try:
        params = resolve_robot(args.robot)
        args.joint_names = robot_joint_names(args.robot)
    except (ValueError, TypeError, FileNotFoundError, ImportError) as err:
        raise _Refused(str(err).splitlines()[0]) from None
    from rmijax.robots.structure import PlanarPointMass

    if args.method == "certified" and not isinstance(params.model.structure, PlanarPointMass):
        raise _Refused(
            f"--method certified: {args.robot}'s default box is not certified in one piece "
            "(the remainder diverges within the first second); call "
            "rmijax.certified_bounds with a smaller box or with splits= (the UR5e's whole "
            "box is certified over the first second in 2 to 32 pieces; docs/methods.md "
            "section 7, rmijax.methods.certified.split_ranking)"
        )
    from rmijax import _checks

    gains = [
        _checks.per_joint(k, v, 1, _checks.default_float())
        for k, v in (("kp", args.kp), ("kd", args.kd))
    ]
    try:
        _checks.check_stable(*gains, args.dt)
    except ValueError as err:
        raise _Refused(str(err).splitlines()[0]) from None
    source = pathlib.Path(args.log)
    if not source.exists():
        raise _Refused(f"no such log or folder: {source}")
    out = pathlib.Path(args.out)
    if out.exists() and not out.is_dir():
        raise _Refused(f"--out {out} is a file, not a folder")
    topics = args.joint_state_topic is not None or args.reference_topic is not None
    if is_log(source):
        if topics and not is_bag(source):
            raise _Refused(f"--joint-state-topic/--reference-topic apply to bags; {source} is not")
        return params, [source], False
    if not source.is_dir():
        raise _Refused(f"{source} is not a log rmijax reads (.csv, .npz, .bag, ROS 2 bag)")
    logs = sorted(p for p in source.iterdir() if is_log(p))
    if not logs:
        raise _Refused(f"{source} holds no logs (.csv, .npz, .bag, ROS 2 bag folders)")
    stems = [p.stem for p in logs]
    twice = sorted({s for s in stems if stems.count(s) > 1})
    if twice:
        raise _Refused(f"{source}: several logs are named {twice[0]!r}; their reports would clash")
    if topics and not all(is_bag(p) for p in logs):
        raise _Refused(
            "--joint-state-topic/--reference-topic apply to bags; the folder holds others"
        )
    return params, logs, True


# --------------------------------------------------------------------------
# One log's report
# --------------------------------------------------------------------------


def _outside_by(values, lower, upper):
    """How far (rad or rad/s) each reading lies outside its band; 0 inside, inf for NaN."""
    import numpy as np

    excess = np.maximum(np.maximum(lower - values, values - upper), 0.0)
    return np.where(np.isnan(values), np.inf, excess)


def _stretches(quiet, dt):
    """``[start, end]`` times (s from the log start) of runs of alarm-free steps."""
    import numpy as np

    edges = np.diff(np.concatenate([[0], quiet.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return [[float(a * dt), float((b - 1) * dt)] for a, b in zip(starts, ends, strict=True)]


def check_log(log, bounds, *, persistence=1, tol=1e-9) -> dict:
    """The report of one log against its bands (what ``report.json`` holds).

    Args:
        log: a :class:`rmijax.io.Log`; bounds: its :class:`~rmijax.Bounds`.
        persistence, tol: as :func:`rmijax.detect`.
    """
    import numpy as np

    from rmijax.detection.detect import detect

    names = log.joint_names
    detection = detect(log.readings, bounds, persistence=persistence, tol=tol)
    lower, upper = np.asarray(bounds.lower), np.asarray(bounds.upper)
    excess = _outside_by(log.readings, lower, upper)
    width = upper - lower
    dt = log.dt

    def output(joint, sensor):
        return f"{names[joint]} {SENSORS[sensor]}"

    first = None
    if detection.first_alarm is not None:
        step = int(round(detection.first_alarm / dt))
        joint, sensor = detection.alarm_output
        by = float(excess[step, joint, sensor])
        first = {
            "time_s": detection.first_alarm,
            "log_time_s": float(log.time[step]),
            "output": output(joint, sensor),
            "reading": float(log.readings[step, joint, sensor]),
            "lower": float(lower[step, joint, sensor]),
            "upper": float(upper[step, joint, sensor]),
            "outside_by": by,
            "unit": UNITS[sensor],
            "outside_by_widths": by / float(width[step, joint, sensor])
            if width[step, joint, sensor] > 0
            else None,
        }
    per_output = {}
    for joint in range(len(names)):
        for sensor in range(2):
            column = excess[:, joint, sensor]
            worst = int(np.argmax(column))
            per_output[output(joint, sensor)] = {
                "alarm_steps": int(detection.alarms[:, joint, sensor].sum()),
                "worst_outside_by": float(column[worst]),
                "worst_time_s": float(worst * dt) if column[worst] > 0 else None,
                "unit": UNITS[sensor],
            }
    quiet = ~detection.alarms.reshape(detection.alarms.shape[0], -1).any(axis=1)
    stretches = _stretches(quiet, dt)
    return {
        "samples": int(log.n_steps + 1),
        "duration_s": float(log.n_steps * dt),
        "dt_s": dt,
        "joint_names": list(names),
        "alarm": first is not None,
        "first_alarm": first,
        "alarm_steps": int((~quiet).sum()),
        "outputs": per_output,
        "alarm_free_stretches_s": stretches,
        "longest_alarm_free_s": max((b - a for a, b in stretches), default=0.0),
        "nan_readings": log.nan_samples,
        "gaps_s": [list(g) for g in log.gaps],
        "source": log.source,
    }


def _markdown(report):
    first = report["first_alarm"]
    lines = [
        f"# rmijax check: {pathlib.Path(report['source']['path']).name}",
        "",
        f"Robot `{report['settings']['robot']}`, method `{report['settings']['method']}` "
        f"({report['settings']['mode']}), {report['samples']} samples "
        f"({report['duration_s']:.2f} s at dt = {report['dt_s']:g} s), joints "
        f"{', '.join(report['joint_names'])}.",
        "",
    ]
    if first is None:
        lines.append("**No alarm**: every reading stayed inside its band.")
    else:
        widths = first["outside_by_widths"]
        relative = f", {widths:.3g} band widths" if widths is not None else ""
        lines.append(
            f"**First alarm at {first['time_s']:.2f} s** (log time {first['log_time_s']:.3f} s) "
            f"on **{first['output']}**: reading {first['reading']:.6g} {first['unit']} against "
            f"[{first['lower']:.6g}, {first['upper']:.6g}], outside by "
            f"{first['outside_by']:.3g} {first['unit']}{relative}."
        )
    lines += [
        "",
        f"Alarm steps: {report['alarm_steps']} of {report['samples']}; longest alarm-free "
        f"stretch {report['longest_alarm_free_s']:.2f} s.",
        "",
        "| output | alarm steps | worst outside by | at [s] |",
        "|---|---|---|---|",
    ]
    for name, row in report["outputs"].items():
        at = "-" if row["worst_time_s"] is None else f"{row['worst_time_s']:.2f}"
        worst = f"{row['worst_outside_by']:.3g} {row['unit']}"
        lines.append(f"| {name} | {row['alarm_steps']} | {worst} | {at} |")
    stretches = report["alarm_free_stretches_s"]
    shown = ", ".join(f"{a:.2f}-{b:.2f}" for a, b in stretches[:20])
    more = f" (and {len(stretches) - 20} more)" if len(stretches) > 20 else ""
    source = report["source"]
    lines += [
        "",
        f"Alarm-free stretches [s]: {shown or 'none'}{more}.",
        "",
        f"Readings: NaN samples {report['nan_readings']} (each alarms); gaps longer than "
        f"1.5 dt: {len(report['gaps_s'])}"
        + (
            f" (first {report['gaps_s'][0][0]:.3f}-{report['gaps_s'][0][1]:.3f} s)"
            if report["gaps_s"]
            else ""
        )
        + f"; put on the grid by `{source['reading_rule']}`, reference interpolated linearly.",
    ]
    if source.get("derived"):
        lines.append(f"Derived: {'; '.join(source['derived'])}.")
    if source.get("ignored"):
        lines.append(f"Not used: {', '.join(source['ignored'])}.")
    if source.get("topics"):
        lines.append(f"Topics: {source['topics']['readings']}, {source['topics']['reference']}.")
    if report.get("figure"):
        lines += ["", f"![bands]({report['figure']})"]
    lines.append("")
    return "\n".join(lines)


def _figure(log, bounds, report, path):
    import numpy as np

    from rmijax.apps.plotting import plot_bands, save_figure
    from rmijax.detection.detect import detect

    first = report["first_alarm"]
    fig = plot_bands(
        log.traj.t,
        bounds,
        y_meas=log.readings,
        relative=True,
        alarm=None if first is None else first["time_s"],
        title=f"{pathlib.Path(report['source']['path']).name}: bands (deviation from nominal), "
        "readings and alarms",
        zoom=1.0,
    )
    alarms = detect(
        log.readings,
        bounds,
        persistence=report["settings"]["persistence"],
        tol=report["settings"]["tol"],
    ).alarms
    t, nominal = np.asarray(log.traj.t), np.asarray(bounds.nominal)
    n = len(log.joint_names)
    for index, ax in enumerate(fig.axes[: 2 * n]):
        sensor, joint = divmod(index, n)
        hit = alarms[:, joint, sensor]
        if hit.any():
            values = log.readings[hit, joint, sensor] - nominal[hit, joint, sensor]
            ax.plot(t[hit], values, "x", color="tab:red", ms=3, label="alarm")
        ax.set_title(f"{log.joint_names[joint]} {SENSORS[sensor]}", fontsize=10)
    save_figure(fig, path)


def _write(out, log, bounds, report, figure=True):
    out.mkdir(parents=True, exist_ok=True)
    report["figure"] = None
    if figure:
        _figure(log, bounds, report, out / "bands.png")
        report["figure"] = "bands.png"
    (out / "report.md").write_text(_markdown(report))
    (out / "report.json").write_text(json.dumps(report, indent=2))


# --------------------------------------------------------------------------
# The command
# --------------------------------------------------------------------------


def _bands(logs, params, args, mesh):
    """Bands of every log: sharded for ``rmi`` and ``certified``, one after another otherwise."""
    from rmijax import fleet
    from rmijax.methods.dispatch import bounds as bounds_of

    noise = dict(noise_lo=-args.noise, noise_hi=args.noise)
    window = {} if args.window is None else {"window": args.window}
    if args.method == "rmi":
        if len(logs) == 1:
            return [
                fleet.rmi_sharded(
                    logs[0].traj,
                    params,
                    mode=args.mode,
                    mesh=mesh,
                    progress=not args.no_progress,
                    **window,
                    **noise,
                )
            ]
        return fleet.rmi_batch(
            [log.traj for log in logs], params, mode=args.mode, mesh=mesh, **window, **noise
        )
    if args.method == "certified":
        return fleet.certified_batch([log.traj for log in logs], params, mesh=mesh, **noise)
    return [
        bounds_of(
            log.traj,
            params,
            method=args.method,
            mode=args.mode,
            readings=log.readings if args.method == "short_window" else None,
            **window,
            **noise,
        )
        for log in logs
    ]


def main(argv=None) -> int:
    """Entry point of ``rmijax check`` (``argv`` without the ``check`` word)."""
    try:
        args = _parser().parse_args(argv)
        import jax

        if not args.float32:
            jax.config.update("jax_enable_x64", True)  # the CLI's choice, not the library's
        cluster = (args.coordinator, args.num_processes, args.process_id)
        if any(v is not None for v in cluster) and not args.distributed:
            raise _Refused("--coordinator/--num-processes/--process-id need --distributed")
        if args.distributed:  # before anything starts JAX's backend
            if not pathlib.Path(args.log).is_dir():
                raise _Refused("--distributed shares a folder of logs between processes")
            # processes share no data; one that ends early waits for the others
            jax.distributed.initialize(*cluster, shutdown_timeout_seconds=_SHUTDOWN_WAIT_S)
        params, paths, folder = _validate(args)
        devices = jax.local_devices()
        if args.devices is not None and args.devices > len(devices):
            raise _Refused(f"--devices {args.devices}: this process has {len(devices)} devices")
    except _Refused as err:
        print(f"rmijax check: {err}", file=sys.stderr)
        return 2
    import matplotlib

    matplotlib.use("Agg")
    from tqdm.auto import tqdm

    from rmijax import fleet
    from rmijax.io import LogError, read_log
    from rmijax.methods.base import DivergedError

    mesh = fleet.device_mesh(devices[: args.devices or len(devices)])
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    read_options = dict(
        robot=params,
        dt=args.dt,
        kp=args.kp,
        kd=args.kd,
        reading_rule=args.reading_rule,
        max_gap=args.max_gap,
        joint_state_topic=args.joint_state_topic,
        reference_topic=args.reference_topic,
        joint_names=args.joint_names,
    )
    settings = {
        "robot": args.robot,
        "method": args.method,
        "mode": args.mode,
        "window": args.window,
        "noise": args.noise,
        "persistence": args.persistence,
        "tol": args.tol,
        "dt": args.dt,
        "kp": args.kp,
        "kd": args.kd,
        "dtype": "float32" if args.float32 else "float64",
        "devices": mesh.size,
        "device_kind": devices[0].device_kind,
    }
    started = time.perf_counter()
    if not folder:
        try:
            log = read_log(paths[0], **read_options)
        except (LogError, ImportError) as err:
            print(f"rmijax check: {err}", file=sys.stderr)
            return 1
        try:
            (bounds,) = _bands([log], params, args, mesh)
        except DivergedError as err:
            print(f"rmijax check: {str(err).splitlines()[0]}", file=sys.stderr)
            return 1
        report = check_log(log, bounds, persistence=args.persistence, tol=args.tol)
        report["settings"] = settings
        _write(out, log, bounds, report, figure=not args.no_figures)
        first = report["first_alarm"]
        what = (
            "no alarm"
            if first is None
            else (f"first alarm {first['time_s']:.2f} s on {first['output']}")
        )
        print(f"{paths[0].name}: {what}; wrote report.md and report.json to {out}")
        return 0

    mine = fleet.my_share(paths) if args.distributed else paths
    todo = [p for p in mine if args.force or not (out / p.stem / "report.json").exists()]
    skipped = len(mine) - len(todo)
    batch = args.batch or 8 * mesh.size
    counts = {"reported": 0, "unreadable": 0, "alarm": 0, "skipped": skipped}
    with tqdm(total=len(todo), desc="logs", unit="log", disable=args.no_progress) as bar:
        for start in range(0, len(todo), batch):
            group, logs = todo[start : start + batch], []
            for path in group:
                try:
                    logs.append((path, read_log(path, **read_options)))
                except (LogError, ImportError) as err:
                    target = out / path.stem
                    target.mkdir(parents=True, exist_ok=True)
                    failure = {"source": {"path": str(path)}, "error": str(err)}
                    failure["settings"] = settings
                    (target / "report.json").write_text(json.dumps(failure, indent=2))
                    counts["unreadable"] += 1
                    bar.update(1)
            if not logs:
                continue
            try:
                all_bounds = _bands([log for _, log in logs], params, args, mesh)
            except DivergedError as err:
                print(f"rmijax check: {str(err).splitlines()[0]}", file=sys.stderr)
                return 1
            for (path, log), bounds in zip(logs, all_bounds, strict=True):
                report = check_log(log, bounds, persistence=args.persistence, tol=args.tol)
                report["settings"] = settings
                _write(out / path.stem, log, bounds, report, figure=not args.no_figures)
                counts["reported"] += 1
                counts["alarm"] += bool(report["alarm"])
                bar.update(1)
    elapsed = time.perf_counter() - started
    summary = _summary(out, mine)
    name = "summary.json" if jax.process_count() == 1 else f"summary.{jax.process_index()}.json"
    (out / name).write_text(json.dumps(summary, indent=2))
    print(
        f"{counts['reported']} logs reported ({counts['alarm']} with alarms), "
        f"{counts['unreadable']} unreadable, {counts['skipped']} already reported; "
        f"{elapsed:.1f} s; summary in {out / name}"
    )
    return 0


def _summary(out, paths):
    """One row per log of the folder (from the reports on disk, old and new)."""
    rows = []
    for path in paths:
        report_path = out / path.stem / "report.json"
        if not report_path.exists():
            continue
        report = json.loads(report_path.read_text())
        first = report.get("first_alarm")
        rows.append(
            {
                "log": path.name,
                "error": report.get("error"),
                "first_alarm_s": None if not first else first["time_s"],
                "output": None if not first else first["output"],
                "alarm_steps": report.get("alarm_steps"),
            }
        )
    return {"logs": rows}


if __name__ == "__main__":
    raise SystemExit(main())
