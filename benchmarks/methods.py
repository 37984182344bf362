"""Compare every bound method on the same work: tightness, safety, detection, cost.

Run from the repository root (float64, CPU):

    python benchmarks/methods.py --json benchmarks/results/methods_cpu.json \\
        --plot benchmarks/results/methods_cpu.png

``--methods`` keeps only some methods (default all a case runs): a new method is
scored on its own and its file merged with the others' by ``--from-json``, which
joins the records of one case from several files.

Cases (``--cases``, default all):

- ``arm2_hold_sine``, ``arm2_hold_ramp``, ``arm2_hold_composite``,
  ``arm2_slow_sine_composite``: the paper's two-joint runs (15 s);
- ``preset2``, ``preset4``, ``preset6``: ``preset_arm(n)`` on slow_sine / sine
  paths (10 s): every method (``certified``'s remainder diverges at 4 and 6 links:
  recorded as diverged, found on the run's first steps);
- ``preset8``, ``preset16``, ``preset32``: the methods that scale
  (``rmijax.SCALABLE_METHODS``); at 16 and 32 links a shorter run (4 s, one
  onset at 2 s), 100 draws and a lighter worst-case search (one time, 3.9 s;
  the Monte-Carlo extremes as starts, 10 iterations), and ``corner_search`` timed
  on single end steps only (``--corner-search-cost``; a whole run would take
  hours; ``benchmarks/results/methods_16.json`` has the 16-link figure).

The true robot of the fault runs is the paper's (masses x1.08, lengths -5 mm).
For each case and method: band width over the worst-case range
(:func:`rmijax.worst_case_table`, started from the Monte-Carlo extremes),
containment of Monte-Carlo runs (all corners when ``K <= 4096``, plus uniform
draws) and of the worst-case points, detection over the fault suite (every
kind, every joint, each onset) and false alarms, and the offline cost per end
step (``certified``, which only computes whole runs: the whole run's seconds over
its steps, the ``cost`` column saying so). Besides, ``corner_search`` against
exhaustive corners on n = 1..6 (:func:`rmijax.corner_search.corner_agreement`).
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)  # the comparison is in float64

import numpy as np  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).parent))

from _common import markdown_table, read_json, run_meta, write_json  # noqa: E402

import rmijax  # noqa: E402
from rmijax.apps.experiments import paper_run, paper_true_parameters  # noqa: E402
from rmijax.evaluation.comparison import Case, compare, step_cost, summary_rows  # noqa: E402
from rmijax.methods.corner_search import corner_agreement, search_robot  # noqa: E402

PAPER_CASES = (
    "arm2_hold_sine",
    "arm2_hold_ramp",
    "arm2_hold_composite",
    "arm2_slow_sine_composite",
)
PRESETS = (2, 4, 6, 8, 16, 32)
CASES = PAPER_CASES + tuple(f"preset{n}" for n in PRESETS)
BIG = 16
"""From this many links on, the shorter protocol."""

COLUMNS = [
    ("case", "case", "{}"),
    ("method", "method", "{}"),
    ("status", "status", "{}"),
    ("ms_per_step", "ms/step", "{:.3g}"),
    ("cost_basis", "cost", "{}"),
    ("enc_width_over_worst", "enc width/worst", "{:.3g}"),
    ("tach_width_over_worst", "tach width/worst", "{:.3g}"),
    ("worst_points_inside", "worst pts in", "{:.3f}"),
    ("mc_inside", "MC in", "{:.4f}"),
    ("mc_clean_runs", "MC clean runs", "{:.3f}"),
    ("detected", "detected", "{:.2f}"),
    ("median_latency", "median latency s", "{:.2f}"),
    ("false_alarms_free", "false alarms (free)", "{}"),
    ("false_alarms_faulty", "false alarms (faulty, pre-onset)", "{}"),
]


def _paths(n):
    return ["slow_sine"] + ["sine"] * (n - 1)


def build_case(name):
    """``(Case, methods, compare options, corner_search cost-only)`` of a case name."""
    if name in PAPER_CASES:
        params, traj = paper_run(name)
        return Case(name, params, traj, paper_true_parameters(params)), rmijax.METHODS, {}, False
    n = int(name.removeprefix("preset"))
    big = n >= BIG
    params = rmijax.preset_arm(n)
    if big:  # the closed-form dynamics written out element-wise compiles for many
        params = search_robot(params)  # minutes at 32 links; solve M qdd = tau - h

    traj = rmijax.trajectory(_paths(n), duration=4.0 if big else 10.0)
    case = Case(name, params, traj, paper_true_parameters(params))
    if n <= 6:
        return case, rmijax.METHODS, {}, False
    methods = tuple(m for m in rmijax.SCALABLE_METHODS if not (big and m == "corner_search"))
    # small batches: a batch's flip loop runs until its slowest track converges
    options = {"options": {"corner_search": {"chunk_size": 8}}}
    if big:
        options.update(
            onsets=(2.0,),
            draws=100,
            times=[3.9],
            worst_options=dict(random_starts=0, iterations=10),
            max_worst_starts=4,
            timing_steps=20,
        )
    return case, methods, options, big


def merge_cases(pieces):
    """The case records of several ``--json`` files, one record per case name.

    Records of the same case from different files (e.g. the six first methods in one
    file, ``certified`` in another) are joined: their methods, refusals and fault rows.
    Both must be the same case (same ``n``, ``K``, ``T``, ``dt`` and fault suite); the
    worst-case table, which scores the width of every method, is the first file's, and
    a later file's table must equal it to rounding (1e-9 relative, 1e-12 absolute: the
    search is seeded, so the same case gives the same table).

    Raises:
        ValueError: two records of one case disagree.
    """
    merged = {}
    for record in (r for piece in pieces for r in piece):
        name = record["case"]
        if name not in merged:
            merged[name] = {**record, "methods": dict(record["methods"])}
            merged[name]["faults"] = [dict(row) for row in record.get("faults", [])]
            for key in ("diverged", "not_supported"):
                merged[name][key] = dict(record.get(key, {}))
            continue
        into = merged[name]
        for key in ("n", "K", "T", "dt"):
            if into[key] != record[key]:
                raise ValueError(f"{name}: {key} differs ({into[key]} and {record[key]})")
        clash = set(into["methods"]) & set(record["methods"])
        if clash:
            raise ValueError(f"{name}: method(s) {sorted(clash)} in two files")
        if record["methods"]:
            mine, theirs = into.get("worst_case"), record["worst_case"]
            if mine is None:
                into["worst_case"] = theirs
            elif not all(
                np.allclose(mine[k], theirs[k], rtol=1e-9, atol=1e-12)
                for k in ("times", "low", "high")
            ):
                raise ValueError(f"{name}: the two files' worst-case tables differ")
            if not into["faults"]:
                into["faults"] = [dict(row) for row in record["faults"]]
            else:
                if [r["fault"] for r in into["faults"]] != [r["fault"] for r in record["faults"]]:
                    raise ValueError(f"{name}: the two files ran different fault suites")
                for row, other in zip(into["faults"], record["faults"], strict=True):
                    row.update({m: other[m] for m in record["methods"]})
        into["methods"].update(record["methods"])
        for key in ("diverged", "not_supported"):
            into[key].update(record.get(key, {}))
    return list(merged.values())


def agreement_rows(sizes, log):
    """corner_search against the exhaustive corner on ``preset_arm(n)``, both modes."""
    rows = []
    for n in sizes:
        params = rmijax.preset_arm(n)
        traj = rmijax.trajectory(_paths(n), duration=3.0)
        end_steps = np.linspace(100, 300, 4 if n >= 5 else 12).astype(int)
        for mode in rmijax.MODES:
            started = time.perf_counter()
            found = corner_agreement(traj, params, end_steps, mode=mode)
            rows.append(
                {
                    "n": n,
                    "mode": mode,
                    "end_steps": int(end_steps.size),
                    "decisions": found["decisions"],
                    "agree": found["agree"],
                    "agree_score": found["agree_score"],
                    "max_abs_error": found["max_abs_error"],
                    "max_rel_error": found["max_rel_error"],
                }
            )
            log(
                f"  agreement n={n} {mode}: {found['agree']:.4f} of {found['decisions']} "
                f"decisions, max rel. error {found['max_rel_error']:.2g} "
                f"({time.perf_counter() - started:.0f} s)"
            )
    return rows


def plot(results, path):
    """One panel per quantity: cost, width over worst case, containment, latency, false alarms.

    A method refused on a case (diverged, not supported) has no bars there; the cost
    panel writes the reason where its bar would be.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = summary_rows(results)
    cases = list(dict.fromkeys(r["case"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    quantities = [
        ("ms_per_step", "offline cost, ms per end step (certified: whole run / steps)", True),
        ("enc_width_over_worst", "encoder band width / worst-case range", True),
        ("tach_width_over_worst", "tachometer band width / worst-case range", True),
        ("mc_inside", "Monte-Carlo samples inside", False),
        ("median_latency", "median detection latency, s", False),
        ("false_alarms_free", "false-alarm steps, fault-free run (+1)", True),
    ]
    fig, axes = plt.subplots(len(quantities), 1, figsize=(12, 3.0 * len(quantities)))
    width = 0.8 / len(methods)
    x = np.arange(len(cases))
    for ax, (key, title, log_scale) in zip(axes, quantities, strict=True):
        for i, method in enumerate(methods):
            values = []
            for case in cases:
                match = [r[key] for r in rows if r["case"] == case and r["method"] == method]
                value = match[0] if match and match[0] is not None else np.nan
                values.append(value + 1 if key == "false_alarms_free" else value)
            at = x + (i - len(methods) / 2 + 0.5) * width
            ax.bar(at, values, width, label=method)
            if key == "ms_per_step":
                for c, case in enumerate(cases):
                    refused = [
                        r["status"]
                        for r in rows
                        if r["case"] == case and r["method"] == method and r["status"] != "scored"
                    ]
                    if refused:
                        ax.text(
                            at[c],
                            0.03,
                            f"{method}: {refused[0]}",
                            rotation=90,
                            fontsize=7,
                            ha="center",
                            va="bottom",
                            transform=ax.get_xaxis_transform(),
                        )
        if key in ("enc_width_over_worst", "tach_width_over_worst"):
            ax.axhline(1.0, color="k", lw=0.8, ls="--")
        if log_scale:
            ax.set_yscale("log")
        ax.set_title(title)
        ax.set_xticks(x, cases, rotation=20, fontsize=8)
    axes[0].legend(ncol=len(methods), fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--cases", nargs="*", choices=CASES, default=list(CASES), help="none: agreement only"
    )
    parser.add_argument(
        "--methods",
        nargs="+",
        choices=rmijax.METHODS,
        help="only these methods (default: every method each case runs)",
    )
    parser.add_argument(
        "--agreement",
        nargs="*",
        type=int,
        default=[1, 2, 3, 4, 5, 6],
        help="link counts for corner_search against exhaustive corners (none: skip)",
    )
    parser.add_argument(
        "--corner-search-cost",
        nargs="*",
        type=int,
        default=[16],
        help="link counts (16 or 32) where corner_search is timed on single end steps "
        "(no 32-link run has finished)",
    )
    parser.add_argument("--draws", type=int, default=1000, help="uniform Monte-Carlo draws")
    parser.add_argument(
        "--cold-only",
        action="store_true",
        help="time whole-run methods (certified) by their only call, compilation included, "
        "instead of a second call: half the cost of a long run",
    )
    parser.add_argument("--json", help="write the results here")
    parser.add_argument("--plot", help="save the figure here (PNG)")
    parser.add_argument(
        "--from-json",
        nargs="+",
        help="print and plot earlier --json files (merged; written to --json if given); "
        "run nothing",
    )
    args = parser.parse_args(argv)

    def log(message):
        print(message, flush=True)

    if args.from_json:
        pieces, agreement, costs, sources = [], [], [], {}
        for path in args.from_json:
            records, piece = read_json(path)
            pieces.append(records["cases"])
            agreement += records["agreement"]
            costs += records["step_costs"]
            sources[path] = piece
        results = merge_cases(pieces)
        # the merge's own command, and each piece's meta (its command reproduces it)
        meta = {**run_meta("benchmarks/methods.py", argv, dtype="float64"), "sources": sources}
        write_json(args.json, {"cases": results, "agreement": agreement, "step_costs": costs}, meta)
    else:
        results, costs, agreement = [], [], []
        meta = run_meta("benchmarks/methods.py", argv, dtype="float64")

        def save():
            records = {"cases": results, "agreement": agreement, "step_costs": costs}
            meta["load_avg"] = [round(x, 2) for x in os.getloadavg()]  # when it ended
            write_json(args.json, records, meta)

        started = time.perf_counter()
        for name in args.cases:
            case, methods, options, cost_only = build_case(name)
            if args.methods:
                methods = tuple(m for m in methods if m in args.methods)
                if not methods:
                    log(f"[{name}] none of {args.methods} runs on this case")
                    continue
            options.setdefault("draws", args.draws)
            options.setdefault("warm", not args.cold_only)
            results.append(compare(case, methods, log=log, **options))
            timed = not args.methods or "corner_search" in args.methods
            if cost_only and timed and case.params.n_joints in args.corner_search_cost:
                cost = step_cost(case, "corner_search", end_steps=(150, 160))
                costs.append({"case": name, "n": case.params.n_joints, **cost})
                log(f"  corner_search: {cost['step_s']:.3g} s per end step (online, compiled)")
            log(f"[{name}] done at {time.perf_counter() - started:.0f} s")
            save()  # a long run keeps what it has
        agreement.extend(agreement_rows(args.agreement, log))
        save()
    print(markdown_table(summary_rows(results), COLUMNS))
    if agreement:
        print()
        print(
            markdown_table(
                agreement,
                [
                    ("n", "n", "{}"),
                    ("mode", "mode", "{}"),
                    ("decisions", "decisions", "{}"),
                    ("agree", "same corner", "{:.4f}"),
                    ("agree_score", "same or tied score", "{:.4f}"),
                    ("max_rel_error", "max error / band width", "{:.2g}"),
                ],
            )
        )
    for cost in costs:
        print(f"\ncorner_search at n={cost['n']}: {cost['step_s']:.3g} s per end step (online)")
    if args.plot:
        plot(results, args.plot)
        print(f"figure: {args.plot}")


if __name__ == "__main__":
    main()
