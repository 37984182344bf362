"""Build and execute notebooks/method_comparison.ipynb (outputs saved in the file).

Run: python notebooks/build_method_comparison.py   (needs nbformat, nbclient, ipykernel)

The numbers come from ``benchmarks/results/methods_cpu.json``, written by
``python benchmarks/methods.py --json benchmarks/results/methods_cpu.json`` (about
an hour on 2 cores) and merged from the files its ``meta.sources`` lists (``certified``
in ``methods_certified.json``, ``--methods certified``); the notebook also computes one
case live.
"""

import pathlib

from _build import build

HERE = pathlib.Path(__file__).parent

CONCLUSIONS = (HERE / "method_comparison_conclusions.md").read_text()

CELLS = [
    (
        "md",
        """# Seven ways to bound a robot's outputs, compared on the same work

Every method below answers the same question: at each step, between which values can the
encoder and tachometer readings of a computed-torque-controlled arm lie when its masses and
lengths are only known within intervals? `docs/methods.md` defines them; all seven sit behind
`rmijax.bounds(traj, params, method=...)`:

| method | idea | cost grows like |
|---|---|---|
| `rmi` | exact RMI: each window step takes the extreme of all `2^p` corners | `2^n` |
| `empirical` | the paper's constant thresholds from fault-free runs | runs |
| `short_window` | RMI over 2 steps from the *measured* state (paper, section 4) | `2^n` / 50 |
| `corner_search` | RMI, extreme corner searched (gradient sign, bit flips) | `p^2` |
| `constant_corners` | envelope of the closed loop run once per constant corner | `2^p` runs |
| `linearized` | first-order parameter sensitivity of the window, plus a margin | `p` |
| `certified` | whole-run Taylor model, proven remainder (planar arm) | `s^n` pieces |

The judge is `rmijax.worst_case`: projected gradient ascent over constant parameters in the box
on the true plant. Its range is *inside* the true reachable range, so a band narrower than it
(ratio < 1) misses a robot that can exist, and a band much wider has lost sensitivity.
`certified` is the one method whose band is proven to hold every constant-parameter run of
the discretised loop; it computes a whole run at once (no window), and its remainder bound
diverges on `preset_arm(4)` and `preset_arm(6)`, where the table says so.""",
    ),
    (
        "code",
        """import json, pathlib, sys
import jax
jax.config.update("jax_enable_x64", True)   # the notebook's choice; rmijax never sets it
%matplotlib inline
import matplotlib.pyplot as plt
import numpy as np
from IPython.display import Markdown, display
import rmijax
from rmijax.evaluation.comparison import summary_rows

sys.path.insert(0, str(pathlib.Path("..", "benchmarks").resolve()))
from methods import COLUMNS
from _common import markdown_table

data = json.loads(pathlib.Path("../benchmarks/results/methods_cpu.json").read_text())
results = data["results"]["cases"]
print("measured on", data["meta"]["device"])
print("command:", data["meta"]["command"])""",
    ),
    (
        "md",
        """## 1. One case, live: the paper's two-joint arm, joint 1 holds, joint 2 follows the sine
Band of every method around the nominal output, joint 2 (the moving one). `short_window` is
built from the readings of a fault-free run of the paper's true robot (masses x1.08, lengths
-5 mm), which is also drawn.""",
    ),
    (
        "code",
        """params = rmijax.paper_arm2()
traj = rmijax.trajectory(["hold", "sine"])
th_true = rmijax.experiments.paper_true_parameters(params)
x_true, y_true = rmijax.simulate(traj, params, th_true)
bands = {}
for method in rmijax.METHODS:
    extra = {"readings": y_true} if method == "short_window" else {}
    bands[method] = rmijax.bounds(traj, params, method=method, **extra)

fig, axes = plt.subplots(2, 1, figsize=(11, 7), sharex=True)
t = np.asarray(traj.t)
nominal = np.asarray(traj.x_n)
for s, (ax, unit) in enumerate(zip(axes, ["encoder, rad", "tachometer, rad/s"])):
    for method, band in bands.items():
        lo = np.asarray(band.lower)[:, 1, s] - nominal[:, 1, s]
        hi = np.asarray(band.upper)[:, 1, s] - nominal[:, 1, s]
        line, = ax.plot(t, hi, lw=1, label=method)
        ax.plot(t, lo, lw=1, color=line.get_color())
    ax.plot(t, np.asarray(x_true)[:, 1, s] - nominal[:, 1, s], "k", lw=1.5, label="true robot")
    ax.set_ylabel("joint 2 " + unit + "\\n(minus nominal)")
    corners = bands["constant_corners"]  # the tightest band sets the scale
    reach = np.abs(np.asarray(corners.upper)[:, 1, s] - nominal[:, 1, s]).max()
    ax.set_ylim(-2.5 * reach, 2.5 * reach)
axes[0].legend(ncol=4, fontsize=8)
axes[1].set_xlabel("t, s");""",
    ),
    (
        "md",
        """## 2. The table
Per case and method (float64, 2-core CPU): offline cost per end step; median band width over
the worst-case range at 8 times (encoder, tachometer; < 1 means a robot that exists falls
outside); the fraction of worst-case points inside the band; Monte-Carlo containment (all
corners when `K <= 4096`, plus uniform draws) as samples inside and runs never outside;
detection over the fault suite (every kind on every joint at two onsets) and false alarms.
`certified` has no end step of its own: its `ms/step` is its whole run's seconds (second
call, compiled) over the run's steps, which the `cost` column says; where it diverged,
`status` says so and the scores are `nan`.""",
    ),
    ("code", """display(Markdown(markdown_table(summary_rows(results), COLUMNS)))"""),
    (
        "md",
        """## 3. One figure per quantity
Cases on the horizontal axis; missing bars are methods that do not run at that size, or
(`certified` at 4 and 6 links) diverged there.""",
    ),
    (
        "code",
        """rows = summary_rows(results)
cases = list(dict.fromkeys(r["case"] for r in rows))
methods = list(dict.fromkeys(r["method"] for r in rows))

def figure(key, title, log=False, transform=lambda v: v, line=None):
    fig, ax = plt.subplots(figsize=(11, 3.2))
    width = 0.8 / len(methods)
    x = np.arange(len(cases))
    for i, method in enumerate(methods):
        values = []
        for case in cases:
            match = [r[key] for r in rows if r["case"] == case and r["method"] == method]
            values.append(transform(match[0]) if match and match[0] is not None else np.nan)
        ax.bar(x + (i - len(methods) / 2 + 0.5) * width, values, width, label=method)
    if line is not None:
        ax.axhline(line, color="k", lw=0.8, ls="--")
    if log:
        ax.set_yscale("log")
    ax.set_xticks(x, cases, rotation=20, fontsize=8)
    ax.set_title(title)
    ax.legend(ncol=len(methods), fontsize=7)
    plt.show()

figure("ms_per_step", "offline cost per end step, ms (1 ms: real time at 1 kHz)",
       log=True, line=1.0)
figure("enc_width_over_worst", "encoder band width / worst-case range", log=True, line=1.0)
figure("tach_width_over_worst", "tachometer band width / worst-case range", log=True, line=1.0)
figure("worst_points_inside", "fraction of worst-case points inside the band", line=1.0)
figure("mc_inside", "Monte-Carlo samples outside the band (fraction, floor 1e-6)", log=True,
       transform=lambda v: max(1.0 - v, 1e-6))
figure("median_latency", "median detection latency over the fault suite, s")
figure("detected", "fraction of the fault suite detected", line=1.0)
figure("false_alarms_free", "false-alarm steps on the fault-free run (+1)", log=True,
       transform=lambda v: v + 1)""",
    ),
    (
        "md",
        """## 4. How often does `corner_search` find the exhaustive corner?
Along exact RMI's tracks of a few end steps of `preset_arm(n)`, every decision is made both
ways (`rmijax.corner_search.corner_agreement`); then the bounds of the same end steps are
compared. "tied" counts a different corner with the same score (equal to the tie
tolerance).""",
    ),
    (
        "code",
        """agreement = data["results"]["agreement"]
display(Markdown(markdown_table(agreement, [
    ("n", "n", "{}"), ("mode", "mode", "{}"), ("decisions", "decisions", "{}"),
    ("agree", "same corner", "{:.4f}"), ("agree_score", "same or tied score", "{:.4f}"),
    ("max_abs_error", "max bound error", "{:.2g}"),
    ("max_rel_error", "max error / band width", "{:.2g}")])))
for cost in data["results"]["step_costs"]:
    print(f"corner_search, {cost['n']} links: {cost['step_s']:.3g} s per end step "
          f"(online, compiled; compile {cost['compile_s']:.0f} s)")""",
    ),
    ("md", CONCLUSIONS),
]


def main():
    build(CELLS, "method_comparison.ipynb")


if __name__ == "__main__":
    main()
