"""The main job's report (``rmijax --out DIR``) kept as a results file with its provenance.

Runs the paper's experiments exactly as the CLI does (figures go to a temporary folder
and are dropped) and writes ``report.json`` under ``results`` with the run's meta, so
the README's paper numbers (detection latencies, containment) come from a committed
artifact.

Run from the repository root (about a minute on 2 cores):

    python benchmarks/paper.py --json benchmarks/results/paper_cpu.json
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
    args = parser.parse_args(argv)

    from rmijax.apps import cli

    with tempfile.TemporaryDirectory() as out:
        code = cli.main(["--out", out, "--no-progress"])
        if code:
            return code
        report = json.loads((pathlib.Path(out) / "report.json").read_text())
    report.pop("figures", None)  # paths in the dropped temporary folder
    meta = run_meta("benchmarks/paper.py", argv, dtype=report["settings"]["dtype"])
    write_json(args.json, report, {**meta, "equivalent": "rmijax --out DIR (report.json)"})
    return 0


if __name__ == "__main__":
    sys.exit(main())
