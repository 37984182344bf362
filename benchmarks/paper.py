"""The main job's report (``rmijax --out DIR``) kept as a results file with its provenance.

Runs the paper's experiments exactly as the CLI does (figures go to a temporary folder
and are dropped) and writes ``report.json`` under ``results`` with the run's meta, so
the README's paper numbers (detection latencies, containment) come from a committed
artifact. With ``--robot NAME`` it runs the real-arm job (``rmijax --robot NAME``)
instead: bands per method and the fault suite's detection table.

Run from the repository root (about a minute on 2 cores; the Panda job about 5-9):

    python benchmarks/paper.py --json benchmarks/results/paper_cpu.json
    python benchmarks/paper.py --robot panda --json benchmarks/results/real_arm_panda_cpu.json
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import tempfile

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from _common import run_meta, write_json  # noqa: E402


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", default=None, help="write results here")
    parser.add_argument("--robot", default=None, help="run the real-arm job for this arm")
    args = parser.parse_args(argv)

    from rmijax.apps import cli

    job = ["--robot", args.robot] if args.robot else []
    with tempfile.TemporaryDirectory() as out:
        code = cli.main([*job, "--out", out, "--no-progress"])
        if code:
            return code
        report = json.loads((pathlib.Path(out) / "report.json").read_text())
    report.pop("figures", None)  # paths in the dropped temporary folder
    dtype = report.get("settings", {}).get("dtype", "float64")
    meta = run_meta("benchmarks/paper.py", argv, dtype=dtype)
    equivalent = f"rmijax {' '.join(job)} --out DIR (report.json)".replace("  ", " ")
    write_json(args.json, report, {**meta, "equivalent": equivalent})
    return 0


if __name__ == "__main__":
    sys.exit(main())
