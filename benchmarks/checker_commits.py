"""The certificate checker's speed at several commits, on one host in one run.

Seconds on a shared host drift by up to 2.8x between days, so a change in the checker's
speed is told only by timing the commits side by side. For each commit this checks out
its tree (``git worktree``, removed afterwards), certifies the paper's pendulum on a
``sine`` for 1 s (``splits=2``, the chosen enclosure, ``propagate="carried"``) with that
commit's ``src`` and times ``check_certificate`` on piece 0 over the first ``--steps``
steps, ``--reps`` times; the commits take turns, so drift in the host's speed reaches
each alike. The row's figure is the best of the reps (the least disturbed); all are kept.

    python benchmarks/checker_commits.py 406e1e3 d761d9a~1 d761d9a 1a8a32c HEAD \
        --json benchmarks/results/checker_commits_cpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

from _common import run_meta, table, write_json

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# Runs in a fresh interpreter on the commit's src: only API that every measured commit has.
_CHILD = """
import json, sys, time
import jax
jax.config.update("jax_enable_x64", True)
import rmijax
from rmijax.methods.certified import certified_bounds
from rmijax.methods.certificate_check import check_certificate
enclosure, steps = sys.argv[1], int(sys.argv[2])
params = rmijax.paper_pendulum()
traj = rmijax.trajectory(["sine"], duration=1.0)
_, cert = certified_bounds(traj, params, splits=2, enclosure=enclosure, propagate="carried")
start = time.perf_counter()
result = check_certificate(cert, traj, params, steps=steps, pieces=[0])
seconds = time.perf_counter() - start
print(json.dumps(dict(ok=bool(result.ok), steps=result.steps, seconds=seconds)))
"""


def _commit(ref):
    return subprocess.run(
        ["git", "rev-parse", "--short", ref], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.strip()


def _time_at(tree, enclosure, steps):
    env = {**os.environ, "PYTHONPATH": os.path.join(tree, "src")}
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, enclosure, str(steps)],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    return json.loads(out.strip().splitlines()[-1])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("commits", nargs="+", help="git revisions to time, in this order")
    parser.add_argument("--enclosure", default="affine", help="certified_bounds enclosure")
    parser.add_argument("--steps", type=int, default=40, help="steps checked per rep")
    parser.add_argument("--reps", type=int, default=3, help="turns over all commits")
    parser.add_argument("--json", help="write the rows here")
    args = parser.parse_args(argv)
    if args.steps < 1 or args.reps < 1:
        parser.error("--steps and --reps must be at least 1")

    commits = [_commit(ref) for ref in args.commits]
    if len(set(commits)) < len(commits):
        parser.error(f"the revisions {args.commits} name one commit twice ({commits})")
    times = {c: [] for c in commits}
    with tempfile.TemporaryDirectory() as scratch:
        trees = {}
        try:
            for commit in commits:
                trees[commit] = os.path.join(scratch, commit)
                subprocess.run(
                    ["git", "worktree", "add", "--detach", "-q", trees[commit], commit],
                    cwd=ROOT,
                    check=True,
                )
            for rep in range(args.reps):
                for commit in commits:
                    run = _time_at(trees[commit], args.enclosure, args.steps)
                    if not run["ok"] or run["steps"] != args.steps:
                        raise SystemExit(f"{commit}: the checker did not accept: {run}")
                    times[commit].append(run["seconds"] / args.steps)
                    print(f"rep {rep} {commit}: {times[commit][-1]:.4f} s per step", flush=True)
        finally:
            for tree in trees.values():
                subprocess.run(["git", "worktree", "remove", "--force", tree], cwd=ROOT)
    rows = [
        dict(
            commit=commit,
            ref=ref,
            enclosure=args.enclosure,
            steps_checked=args.steps,
            best_s_per_step=round(min(times[commit]), 4),
            s_per_step=[round(t, 4) for t in times[commit]],
        )
        for ref, commit in zip(args.commits, commits, strict=True)
    ]
    columns = [
        ("ref", "ref", "{}"),
        ("commit", "commit", "{}"),
        ("best_s_per_step", "best s/step", "{:.4f}"),
    ]
    print(table(rows, columns))
    write_json(args.json, rows, run_meta("benchmarks/checker_commits.py", argv, dtype="float64"))
    return rows


if __name__ == "__main__":
    main()
