"""Shared helpers of the benchmark scripts: timing, machine description, JSON and tables."""

from __future__ import annotations

import datetime
import json
import os
import platform
import resource
import shlex
import subprocess
import sys
import time

import numpy as np

REAL_TIME_BUDGET_S = 1e-3
"""The real-time reference: one tick of a 1 kHz torque loop (SPEC section 8)."""


def time_calls(fn, args_for_call, *, calls, max_seconds=None):
    """Median and p99 seconds of ``fn(*args_for_call(i))`` (blocked until ready).

    Stops early after ``max_seconds`` (at least 2 calls), and says how many ran.
    """
    times = []
    started = time.perf_counter()
    for i in range(calls):
        t0 = time.perf_counter()
        out = fn(*args_for_call(i))
        _block(out)
        times.append(time.perf_counter() - t0)
        elapsed = time.perf_counter() - started
        if max_seconds is not None and len(times) >= 2 and elapsed > max_seconds:
            break
    times = np.asarray(times)
    return {
        "p50_s": float(np.median(times)),
        "p99_s": float(np.percentile(times, 99)),
        "calls": int(times.size),
    }


def _block(out):
    import jax

    jax.block_until_ready(out)


def peak_rss_mb():
    """Peak resident memory of this process so far, in MiB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def device():
    """A short description of the machine the numbers come from."""
    import jax

    dev = jax.devices()[0]
    cpu = platform.processor() or platform.machine()
    return f"{dev.platform}:{dev.device_kind} ({os.cpu_count()} cores, {cpu})"


def run_meta(script, argv=None, *, dtype):
    """What a results file needs to be reproduced: command, commit, date, machine, dtype.

    ``command`` is the exact command line that wrote the file (run from the repository
    root); ``commit`` the git HEAD of the code that ran, with ``+dirty`` when the work
    tree had uncommitted changes to tracked files other than ``benchmarks/results/``
    (listed in ``uncommitted_changes``);
    ``load_avg`` the machine's load when the run ended.
    """
    import jax

    argv = sys.argv[1:] if argv is None else list(argv)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=root,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        changed = [line[3:] for line in dirty.splitlines() if line.strip()]
        # results files are what benchmarks write (a run that writes after every case
        # sees its own earlier output): they do not make the code that ran dirty
        changed = [path for path in changed if not path.startswith("benchmarks/results/")]
        commit += "+dirty" if changed else ""
    except (OSError, subprocess.CalledProcessError):
        commit, changed = "unknown", []
    return {
        "command": " ".join(["python", script] + [shlex.quote(a) for a in argv]),
        "commit": commit,
        **({"uncommitted_changes": changed} if changed else {}),
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "device": device(),
        "machine": _machine(),
        "dtype": dtype,
        "jax": jax.__version__,
        # 1, 5 and 15 min load averages when the run ended: on a shared machine a
        # load above the core count means other jobs took time from the timed one.
        "load_avg": [round(x, 2) for x in os.getloadavg()],
    }


def _machine():
    """CPU model, architecture and core count (no host name)."""
    model = platform.processor() or ""
    try:
        with open("/proc/cpuinfo") as handle:
            for line in handle:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return f"{model or 'unknown CPU'}, {platform.machine()}, {os.cpu_count()} cores"


def host_reference(calls=200):
    """How fast this host is when the results are written, to compare runs made apart.

    The same shared 2-core VM ran the same timed code 1.6x slower or faster within
    hours, so a timing alone does not say whether code or host changed. Two fixed
    workloads, timed when a results file is written (the end of its run):

    - ``matmul_gflops``: float32 256 x 256 matrix products (jitted), ``2 * 256^3``
      flops each, at the median call time: the arithmetic speed;
    - ``dispatch_us``: the median wall time of a jitted function that adds one to 8
      numbers (one tiny kernel): the fixed cost of a call (dispatch and thread
      hand-offs), which bounds the shortest tick.
    """
    import jax
    import jax.numpy as jnp

    a = jnp.asarray(np.random.default_rng(0).standard_normal((256, 256)), jnp.float32)
    matmul = jax.jit(lambda x: x @ x)
    bump = jax.jit(lambda x: x + 1)
    results = {}
    for name, fn, arg in (("matmul", matmul, a), ("dispatch", bump, a[0, :8])):
        fn(arg).block_until_ready()
        times = []
        for _ in range(calls):
            start = time.perf_counter()
            fn(arg).block_until_ready()
            times.append(time.perf_counter() - start)
        results[name] = float(np.median(times))
    return {
        "matmul_gflops": round(2 * 256**3 / results["matmul"] / 1e9, 2),
        "dispatch_us": round(results["dispatch"] * 1e6, 1),
    }


def write_json(path, records, meta):
    """Write ``{"meta": meta, "results": records}``; the meta gains the host's
    :func:`host_reference` speed, measured now (the end of the run)."""
    if path:
        meta = {**meta, "host_reference": host_reference()}
        with open(path, "w") as handle:
            json.dump({"meta": meta, "results": records}, handle, indent=2)


def read_json(path):
    """``(records, meta)`` of a file written by :func:`write_json`."""
    with open(path) as handle:
        data = json.load(handle)
    return data["results"], data["meta"]


def markdown_table(records, columns):
    """The same table as :func:`table`, in Markdown."""
    lines = [
        "| " + " | ".join(h for _, h, _ in columns) + " |",
        "|" + "---|" * len(columns),
    ]
    for rec in records:
        lines.append(
            "| " + " | ".join(fmt.format(rec[key]).strip() for key, _, fmt in columns) + " |"
        )
    return "\n".join(lines)


def table(records, columns):
    """A plain-text table of ``records`` with ``columns = [(key, header, fmt)]``."""
    head = " | ".join(h for _, h, _ in columns)
    lines = [head, "-" * len(head)]
    for rec in records:
        lines.append(" | ".join(fmt.format(rec[key]) for key, _, fmt in columns))
    return "\n".join(lines)
