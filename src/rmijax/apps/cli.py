"""Command line: reproduce the paper's experiments and write figures and a report.

rmijax --out rmijax-output          # the default run (a minute or two on 2 cores)
rmijax --quick --out /tmp/smoke     # 6 s runs, fewer draws: a smoke test
rmijax check LOG --robot NAME       # reports for recorded logs (rmijax.apps.check)
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import sys
import time
import warnings

__all__ = ["main"]

METHOD_TITLES = {
    "rmi_coupled": "RMI coupled",
    "rmi_per_joint": "RMI per_joint",
    "constant": "constant thresholds",
}


class _Parser(argparse.ArgumentParser):
    """An argument parser whose every error is one line on stderr and exit code 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _parser():
    parser = _Parser(
        prog="rmijax",
        description=(
            "Reproduce the paper's RMI experiments: pendulum and two-joint bands "
            "(figures 3-14), the fault runs of figures 15-20, a detection table for every "
            "fault kind on both joints (RMI coupled and per_joint against constant "
            "thresholds) and containment of constant-parameter runs. Writes PNGs, "
            "report.json and report.md to --out."
        ),
        epilog="Recorded logs: rmijax check LOG --robot NAME --out DIR (rmijax check --help).",
    )
    parser.add_argument("--out", default="rmijax-output", help="output folder (created)")
    parser.add_argument(
        "--quick",
        action="store_true",
        help="6 s runs and 20 draws instead of 15 s and 100: a smoke test",
    )
    parser.add_argument(
        "--draws",
        type=int,
        default=None,
        help="uniform true-parameter draws for containment (plus all corners)",
    )
    parser.add_argument(
        "--runs", type=int, default=20, help="fault-free runs that tune the constant thresholds"
    )
    parser.add_argument(
        "--safety", type=float, default=1.2, help="safety factor of the constant thresholds"
    )
    parser.add_argument("--onset", type=float, default=3.0, help="fault onset in s")
    parser.add_argument(
        "--persistence", type=int, default=1, help="consecutive out-of-band steps for an alarm"
    )
    parser.add_argument(
        "--float32", action="store_true", help="compute in float32 (default float64)"
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    arm = parser.add_argument_group(
        "real arm", "with --robot, run the real-arm job instead of the paper's experiments"
    )
    arm.add_argument(
        "--robot",
        default=None,
        help="a shipped arm (panda, iiwa14, ur5e) or a URDF/MJCF file: pick-and-place move, "
        "bands of every output per method, every fault kind on every joint, figures, report",
    )
    arm.add_argument(
        "--methods",
        default="rmi,linearized,empirical",
        help="comma-separated band methods the real-arm job compares",
    )
    arm.add_argument(
        "--segment-time",
        type=float,
        default=1.0,
        help="seconds per waypoint segment of the pick-and-place move (7 segments)",
    )
    return parser


def _real_arm(args) -> int:
    """``rmijax --robot NAME``: check the job's own options (the shared ones are checked by
    :func:`_check_options` before), then run the job."""
    import pathlib

    from rmijax.methods.dispatch import METHODS
    from rmijax.robots.loaders import SHIPPED

    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
    unknown = [m for m in methods if m not in METHODS]
    if not methods or unknown:
        print(f"--methods: unknown method(s) {unknown}; choose from {METHODS}", file=sys.stderr)
        return 2
    if args.robot not in SHIPPED and not pathlib.Path(args.robot).is_file():
        print(
            f"--robot: {args.robot!r} is neither a shipped arm {SHIPPED} nor an existing "
            "URDF/MJCF file",
            file=sys.stderr,
        )
        return 2
    if not args.segment_time > 0:
        print("--segment-time must be a positive time in s", file=sys.stderr)
        return 2
    import jax

    if not args.float32:
        jax.config.update("jax_enable_x64", True)  # the CLI's choice, not the library's
    import matplotlib

    matplotlib.use("Agg")
    from rmijax.apps import real_arm

    report = real_arm.run(
        args.robot,
        args.out,
        methods=methods,
        segment_time=args.segment_time,
        persistence=args.persistence,
        progress=not args.no_progress,
    )
    print((pathlib.Path(args.out) / "report.md").read_text())
    print(f"done in {report['seconds']:.0f} s; figures and report in {args.out}")
    return 0


def _latency(detection):
    if detection.latency is None:
        return "missed"
    return f"{detection.latency:.2f}"


def _pct(value):
    return f"{100 * value:.2f}%"


def _check_options(parser, args):
    """Validate every option before any work: a bad one ends in ``parser.error`` (exit 2)."""
    duration = 6.0 if args.quick else 15.0
    if args.draws is not None and args.draws < 0:
        parser.error(f"--draws must be an integer >= 0 (uniform draws), got {args.draws}")
    if args.runs < 1:
        parser.error(f"--runs must be an integer >= 1 (fault-free runs), got {args.runs}")
    if not (math.isfinite(args.safety) and args.safety > 0):
        parser.error(f"--safety must be a positive finite factor, got {args.safety}")
    if not (math.isfinite(args.onset) and 0 < args.onset < duration):
        parser.error(
            f"--onset must lie inside the {duration:g} s run (0 < onset < {duration:g}), "
            f"got {args.onset}"
        )
    if args.persistence < 1:
        parser.error(
            f"--persistence must be an integer >= 1 (consecutive steps), got {args.persistence}"
        )
    out = pathlib.Path(args.out)
    if out.exists() and not out.is_dir():
        parser.error(f"--out {str(out)!r} is an existing file; give a folder (it is created)")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        parser.error(f"--out {str(out)!r} cannot be created: {err.strerror or err}")
    if not os.access(out, os.W_OK):
        parser.error(f"--out {str(out)!r} is not writable")
    return duration, out


def main(argv=None) -> int:
    """Run the paper's experiments (or, with --robot, the real-arm job; ``check``: logs).

    Every failure is one line on stderr and exit code 2.
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] == "check":  # `rmijax check LOG ...`: reports for recorded logs
        from rmijax.apps.check import main as check

        return check(argv[1:])
    parser = _parser()
    args = parser.parse_args(argv)
    duration, out = _check_options(parser, args)
    if args.robot is not None:

        def job():
            return _real_arm(args)

    else:

        def job():
            return _run(args, duration, out)

    try:
        return job()
    except KeyboardInterrupt:
        print(f"{parser.prog}: interrupted", file=sys.stderr)
        return 130
    except Exception as err:  # one line, never a traceback (RMIJAX_TRACEBACK=1 shows it)
        if os.environ.get("RMIJAX_TRACEBACK"):
            raise
        first = str(err).strip().splitlines()[0] if str(err).strip() else ""
        print(
            f"{parser.prog}: error: {type(err).__name__}: {first} "
            "(set RMIJAX_TRACEBACK=1 for the traceback)",
            file=sys.stderr,
        )
        return 2


def _run(args, duration, out) -> int:
    import jax

    if not args.float32:
        jax.config.update("jax_enable_x64", True)  # the CLI's choice, not the library's
    import matplotlib

    matplotlib.use("Agg")
    from tqdm.auto import tqdm

    from rmijax.apps import experiments as ex
    from rmijax.apps.plotting import plot_bands, plot_comparison, save_figure
    from rmijax.detection.detect import detect
    from rmijax.plant import Fault, simulate

    draws = args.draws if args.draws is not None else (20 if args.quick else 100)
    started = time.perf_counter()
    report = {
        "settings": {
            "duration_s": duration,
            "draws": draws,
            "runs": args.runs,
            "safety": args.safety,
            "onset_s": args.onset,
            "persistence": args.persistence,
            "dtype": "float32" if args.float32 else "float64",
        },
        "bands": {},
        "containment": {},
        "paper_fault_runs": {},
        "fault_table": [],
        "figures": [],
    }
    figures = report["figures"]
    quiet = args.no_progress

    # 1. Bands for the paper's trajectories (figures 3-14) and containment.
    all_bands = {}
    bar = tqdm(ex.PAPER_RUNS.items(), desc="paper runs", disable=quiet)
    for name, (_, paths, figs) in bar:
        bar.set_postfix_str(name)
        params, traj = ex.paper_run(name, duration=duration)
        bands = all_bands[name] = ex.method_bands(traj, params, runs=args.runs, safety=args.safety)
        table = ex.containment_table(traj, params, bands, draws=draws)
        report["containment"][name] = table
        width = bands["rmi_coupled"].width
        report["bands"][name] = {
            "paths": list(paths),
            "paper_figures": figs,
            "max_width_coupled": jax.numpy.max(width, axis=0).tolist(),
        }
        path = out / f"bands_{name}.png"
        save_figure(
            plot_bands(
                traj.t,
                bands["rmi_coupled"],
                relative=True,
                title=f"{name}: RMI coupled bands (deviation from nominal)",
            ),
            path,
        )
        figures.append(path.name)

    # 2. The paper's fault runs (figures 15-20) on the two-joint arm, hold/sine.
    params, traj = ex.paper_run("arm2_hold_sine", duration=duration)
    th_true = ex.paper_true_parameters(params)
    bands = all_bands["arm2_hold_sine"]  # computed in step 1
    cases = {
        "fault_free": [],
        "stuck_sensors_joint1": [Fault("stuck_sensors", 0, args.onset)],
        "stuck_sensors_joint2": [Fault("stuck_sensors", 1, args.onset)],
    }
    for case, faults in cases.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a diverging run is expected
            x_true, y_meas = simulate(traj, params, th_true, faults=faults)
        onset = args.onset if faults else None
        results = {
            m: detect(y_meas, b, onset=onset, persistence=args.persistence, x_true=x_true)
            for m, b in bands.items()
        }
        report["paper_fault_runs"][case] = {
            m: {
                "first_alarm_s": d.first_alarm,
                "latency_s": d.latency,
                "false_alarms": d.false_alarms,
                "alarm_output": d.describe_output(d.alarm_output),
                "true_exit_s": d.true_exit,
                "true_exit_output": d.describe_output(d.true_exit_output),
            }
            for m, d in results.items()
        }
        path = out / f"fault_{case}.png"
        title = f"{case}: RMI coupled band, true robot (masses x1.08, lengths -5 mm)"
        save_figure(
            plot_bands(
                traj.t,
                bands["rmi_coupled"],
                x_true=x_true,
                y_meas=y_meas,
                onset=onset,
                alarm=results["rmi_coupled"].first_alarm,
                title=title,
                relative=True,
                zoom=1.0,
            ),
            path,
        )
        figures.append(path.name)
        if faults:
            path = out / f"compare_{case}.png"
            save_figure(
                plot_comparison(
                    traj.t,
                    bands["rmi_coupled"],
                    bands["constant"],
                    y_meas=y_meas,
                    onset=onset,
                    alarms={
                        "RMI": results["rmi_coupled"].first_alarm,
                        "constant": results["constant"].first_alarm,
                    },
                    title=f"{case}: RMI coupled band vs constant thresholds",
                    zoom=1.0,
                ),
                path,
            )
            figures.append(path.name)

    # 3. Every fault kind on both joints.
    suite = ex.default_fault_suite(params.n_joints, args.onset)
    with tqdm(total=len(suite), desc="fault suite", disable=quiet) as bar:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            rows = ex.fault_table(
                traj,
                params,
                th_true,
                bands,
                suite,
                persistence=args.persistence,
                progress=lambda done, total: bar.update(1),
            )
    for row in rows:
        report["fault_table"].append(
            {
                "fault": row.fault.label,
                **{
                    m: {
                        "latency_s": d.latency,
                        "false_alarms": d.false_alarms,
                        "alarm_output": d.describe_output(d.alarm_output),
                    }
                    for m, d in row.results.items()
                },
            }
        )
    report["elapsed_s"] = time.perf_counter() - started
    (out / "report.json").write_text(json.dumps(report, indent=2))
    (out / "report.md").write_text(_markdown(report, rows))
    print(
        f"wrote {len(figures)} figures, report.json and report.md to {out} "
        f"in {report['elapsed_s']:.0f} s"
    )
    print(_markdown_fault_runs(report))
    return 0


def _markdown_fault_runs(report):
    lines = [
        "| run | method | first alarm [s] | latency [s] | false alarms | alarm by | "
        "true state leaves [s] |",
        "|---|---|---|---|---|---|---|",
    ]
    for case, methods in report["paper_fault_runs"].items():
        for method, d in methods.items():
            lines.append(
                f"| {case} | {METHOD_TITLES[method]} | {_opt(d['first_alarm_s'])} | "
                f"{_opt(d['latency_s'])} | {d['false_alarms']} | {d['alarm_output']} | "
                f"{_opt(d['true_exit_s'])} |"
            )
    return "\n".join(lines)


def _opt(value):
    return "-" if value is None else f"{value:.2f}"


def _markdown(report, rows):
    s = report["settings"]
    lines = [
        "# rmijax: the paper's experiments",
        "",
        f"Runs of {s['duration_s']:g} s at dt = 0.01 s, Kp = 100, Kd = 20, window 100, "
        f"{s['dtype']}. True robot for the fault runs: every mass x1.08, every length "
        f"-0.005 m. Faults at {s['onset_s']:g} s; alarm persistence {s['persistence']}. "
        f"Constant thresholds: {s['runs']} fault-free runs in the box, safety x{s['safety']}.",
        "",
        "## Paper fault runs (figures 15-20: two-joint arm, joint 1 hold, joint 2 sine)",
        "",
        _markdown_fault_runs(report),
        "",
        "## Every fault kind on both joints (latency in s / false alarms before onset)",
        "",
        "| fault | " + " | ".join(METHOD_TITLES.values()) + " |",
        "|---|" + "---|" * len(METHOD_TITLES),
    ]
    for row in rows:
        cells = [
            f"{_latency(row.results[m])} / {row.results[m].false_alarms}" for m in METHOD_TITLES
        ]
        lines.append(f"| {row.fault.label} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "`missed`: no alarm after the onset. RMI per_joint bands do not contain the true "
        "plant for two joints (SPEC section 4): their false alarms make their latencies "
        "meaningless.",
        "",
        f"## Containment: all corners + {s['draws']} uniform constant true robots",
        "",
        "Fraction of (run, step, output) samples inside / runs with no violation / worst "
        "violation as a fraction of the band width.",
        "",
        "| run | " + " | ".join(METHOD_TITLES.values()) + " |",
        "|---|" + "---|" * len(METHOD_TITLES),
    ]
    for name, table in report["containment"].items():
        cells = [
            f"{_pct(table[m]['inside'])} / {_pct(table[m]['clean_runs'])} / {table[m]['worst']:.3f}"
            for m in METHOD_TITLES
        ]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += ["", "## Figures", ""] + [f"- `{f}`" for f in report["figures"]]
    lines += ["", f"Total time {report['elapsed_s']:.0f} s.", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
