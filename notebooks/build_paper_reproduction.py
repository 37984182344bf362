"""Build and execute notebooks/paper_reproduction.ipynb (outputs saved in the file).

Run: python notebooks/build_paper_reproduction.py   (needs nbformat, nbclient, ipykernel)
"""

from _build import build

CELLS = [
    (
        "md",
        """# Reproducing "Dynamic sensor-based fault detection for robots" with rmijax

RMI (Reachable Measurement Intervals) bounds, at every step, the encoder and tachometer
readings a computed-torque-controlled arm can reach when its masses and lengths are only
known within intervals. This notebook walks through the paper's experiments with the
library's own functions (no copy of library code): the pendulum and two-joint bands, the
fault runs of figures 15-20, and RMI against the paper's constant thresholds.""",
    ),
    (
        "code",
        """import jax
jax.config.update("jax_enable_x64", True)   # the notebook's choice; rmijax never sets it
%matplotlib inline
import numpy as np
import rmijax
from rmijax.apps import experiments as ex
from rmijax.apps.plotting import plot_bands, plot_comparison"""
    ),
    (
        "md",
        """## 1. The pendulum (figures 3, 5): sine trajectory
`m = 10 kg` in `[9, 11]`, `l = 1 m` in `[0.99, 1.01]`, `Kp = 100`, `Kd = 20`, `dt = 0.01 s`,
window of 100 steps. The bands are shown as deviations from the nominal output. Note how
the tachometer band widens near the peaks of the motion.""",
    ),
    (
        "code",
        """pendulum = rmijax.paper_pendulum()
traj = rmijax.trajectory("sine")
bounds = rmijax.rmi(traj, pendulum)
print("band half-width, max over the run: encoder %.4f rad, tachometer %.4f rad/s"
      % tuple(np.asarray(bounds.width).max(axis=(0, 1)) / 2))
plot_bands(traj.t, bounds, relative=True, title="pendulum, sine");""",
    ),
    (
        "md",
        """## 2. The two-joint arm (figures 4, 6, 9-14)
Link 1: `m1 = 12 kg` in `[11, 13]`, `l1 = 1.5 m` in `[1.49, 1.51]`; link 2 as the pendulum.
Joint 1 holds (`hold`) while joint 2 follows the sine, then both move. `coupled` mode is
exact (the default); `per_joint` is the paper's simplification.""",
    ),
    (
        "code",
        """arm = rmijax.paper_arm2()
hold_sine = rmijax.trajectory(["hold", "sine"])
coupled = rmijax.rmi(hold_sine, arm)
per_joint = rmijax.rmi(hold_sine, arm, mode="per_joint")
plot_bands(hold_sine.t, coupled, relative=True, title="two-joint arm, hold / sine, coupled");""",
    ),
    (
        "code",
        """both = rmijax.trajectory(["slow_sine", "composite"])
plot_bands(both.t, rmijax.rmi(both, arm), relative=True,
           title="two-joint arm, slow_sine / composite (figures 11-14)");""",
    ),
    (
        "md",
        """## 3. Do the bands contain the real robot?
Constant true parameters anywhere in the box: all 16 corners plus 200 uniform draws.
`coupled` contains ~99.7% of samples (not 100%: the window restarts at the nominal state
and corners are chosen greedily); `per_joint` does not contain the true plant for two
joints, because it takes the other joint from the nominal trajectory.""",
    ),
    (
        "code",
        """draws = rmijax.monte_carlo_parameters(arm, 200, seed=0)
states, _ = rmijax.simulate(hold_sine, arm, draws)
for name, b in [("coupled", coupled), ("per_joint", per_joint)]:
    c = rmijax.containment(states, b)
    print(f"{name:10s} inside {c['inside']:.2%}  clean runs {c['clean_runs']:.1%}  "
          f"worst violation {c['worst']:.3f} band widths")""",
    ),
    (
        "md",
        """## 4. The paper's fault runs (figures 15-20)
The true robot has every mass x1.08 and every length -5 mm. Faults: both sensors of a
joint stick at 3.0 s (the encoder holds its reading, the tachometer reads 0).""",
    ),
    (
        "code",
        """th_true = ex.paper_true_parameters(arm)
constant = rmijax.empirical_thresholds(hold_sine, arm, runs=20, safety=1.2)
x_true, y_meas = rmijax.simulate(hold_sine, arm, th_true)
print("fault-free, RMI:     ", rmijax.detect(y_meas, coupled, x_true=x_true).summary())
print("fault-free, constant:", rmijax.detect(y_meas, constant, x_true=x_true).summary())""",
    ),
    (
        "code",
        """import warnings
runs = {}
for joint in (1, 0):
    fault = rmijax.Fault("stuck_sensors", joint, 3.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)   # the faulty arm may run away
        x_true, y_meas = rmijax.simulate(hold_sine, arm, th_true, faults=[fault])
    runs[joint] = (x_true, y_meas)
    for name, b in [("RMI", coupled), ("constant", constant)]:
        report = rmijax.detect(y_meas, b, onset=3.0, x_true=x_true)
        print(f"{fault.label:24s} {name:9s}", report.summary())""",
    ),
    (
        "md",
        """Joint 2's fault is caught at once. Joint 1's frozen readings stay inside its own
band (it is asked to hold still); the fault shows up about 2 s later on joint 2's encoder
with RMI, and almost 4 s later with constant thresholds, while the true joint 1 leaves
its band within about 0.6 s.""",
    ),
    (
        "code",
        """x_true, y_meas = runs[0]
d = rmijax.detect(y_meas, coupled, onset=3.0, x_true=x_true)
plot_bands(hold_sine.t, coupled, x_true=x_true, y_meas=y_meas, relative=True, zoom=1.0,
           onset=3.0, alarm=d.first_alarm, title="stuck sensors on joint 1 at 3 s");""",
    ),
    (
        "code",
        """c = rmijax.detect(y_meas, constant, onset=3.0)
plot_comparison(hold_sine.t, coupled, constant, y_meas=y_meas, onset=3.0, zoom=1.0,
                alarms={"RMI": d.first_alarm, "constant": c.first_alarm},
                title="RMI band vs constant thresholds, stuck sensors on joint 1");""",
    ),
    (
        "md",
        """## 5. Every fault kind on both joints
Latency (s) after the 3 s onset, or `missed`; false alarms before the onset in brackets.
The full table with `per_joint` and containment for every paper run is what the command
line `rmijax --out DIR` writes to `DIR/report.md`.""",
    ),
    (
        "code",
        """bands = {"RMI coupled": coupled, "constant": constant}
with warnings.catch_warnings():
    warnings.simplefilter("ignore", RuntimeWarning)
    rows = ex.fault_table(hold_sine, arm, th_true, bands, ex.default_fault_suite(2, 3.0))
print(f"{'fault':30s} {'RMI coupled':>16s} {'constant':>16s}")
for row in rows:
    cells = [("missed" if r.latency is None else f"{r.latency:.2f} s") + f" ({r.false_alarms})"
             for r in row.results.values()]
    print(f"{row.fault.label:30s} {cells[0]:>16s} {cells[1]:>16s}")""",
    ),
    (
        "md",
        """## What this shows
- With exact (`coupled`) RMI bands the fault-free run raises no alarm, and a stuck joint 1
  is caught about 2 s earlier than with the paper's constant thresholds, through joint 2.
- RMI is not faster on every fault: where its band is wider than the constant one
  (joint 1's tachometer band is wide by design, SPEC section 10) a slow drift or a stuck
  tachometer is seen later. The constant thresholds, however, are tuned on this very
  trajectory; RMI's bands follow any motion without retuning.
- Faults that leave every reading near the truth (a stuck encoder or a lock on a joint that
  is asked to hold still) are missed by every method: no threshold can see them.
- `per_joint` bands (the paper's) raise false alarms on the real two-joint robot.""",
    ),
]


def main():
    build(CELLS, "paper_reproduction.ipynb")


if __name__ == "__main__":
    main()
