"""Figures: bands with nominal, true and measured paths; RMI against constant thresholds.

Each function draws one figure and returns it; ``save_figure`` writes a PNG.
The CLI and the notebooks call the same functions.
"""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np

__all__ = ["plot_bands", "plot_comparison", "save_figure"]

_SENSORS = (("encoder", "rad"), ("tachometer", "rad/s"))


def _axes_grid(n_joints, sensors, figsize=None):
    fig, axes = plt.subplots(
        len(sensors),
        n_joints,
        figsize=figsize or (5.2 * n_joints, 2.9 * len(sensors)),
        sharex=True,
        squeeze=False,
    )
    return fig, axes


def _mark(ax, onset, alarm):
    if onset is not None:
        ax.axvline(onset, color="k", ls="--", lw=0.8, label="fault onset")
    if alarm is not None:
        ax.axvline(alarm, color="tab:red", ls=":", lw=1.2, label="first alarm")


def _zoom(ax, low, high, zoom):
    """Limit the y axis to the band plus ``zoom`` times its largest width on either side."""
    if zoom is None:
        return
    margin = zoom * max(float(np.max(high - low)), 1e-12)
    ax.set_ylim(float(np.min(low)) - margin, float(np.max(high)) + margin)


def plot_bands(
    t,
    bounds,
    *,
    x_true=None,
    y_meas=None,
    joints=None,
    sensors=(0, 1),
    relative=False,
    onset=None,
    alarm=None,
    title=None,
    zoom=None,
):
    """RMI bands per joint and sensor, with nominal, true and measured paths (paper figures).

    Args:
        t: (T+1,) time in s.
        bounds: :class:`~rmijax.methods.base.Bounds` (T+1, n, 2).
        x_true, y_meas: optional (T+1, n, 2) true states and readings.
        joints: which joints (0-based) to draw; default all.
        sensors: which sensors, 0 encoder and/or 1 tachometer.
        relative: draw deviations from the nominal instead of absolute values.
        onset, alarm: times in s to mark with vertical lines.
        title: figure title.
        zoom: if given, limit each y axis to the band plus ``zoom`` times its
            largest width on either side (paths that run away leave the view,
            as in the paper's fault figures).

    Returns:
        The matplotlib figure.
    """
    t = np.asarray(t)
    lower, upper = np.asarray(bounds.lower), np.asarray(bounds.upper)
    nominal = np.asarray(bounds.nominal)
    joints = range(lower.shape[1]) if joints is None else joints
    joints = list(joints)
    fig, axes = _axes_grid(len(joints), sensors)
    for col, joint in enumerate(joints):
        for row, sensor in enumerate(sensors):
            ax = axes[row, col]
            base = nominal[:, joint, sensor] if relative else 0.0
            ax.fill_between(
                t,
                lower[:, joint, sensor] - base,
                upper[:, joint, sensor] - base,
                color="tab:blue",
                alpha=0.25,
                lw=0,
                label="RMI band",
            )
            ax.plot(t, nominal[:, joint, sensor] - base, color="tab:blue", lw=0.8, label="nominal")
            if x_true is not None:
                ax.plot(
                    t,
                    np.asarray(x_true)[:, joint, sensor] - base,
                    color="tab:orange",
                    lw=1.0,
                    label="true",
                )
            if y_meas is not None:
                ax.plot(
                    t,
                    np.asarray(y_meas)[:, joint, sensor] - base,
                    color="tab:green",
                    lw=0.8,
                    ls="--",
                    label="measured",
                )
            _mark(ax, onset, alarm)
            _zoom(ax, lower[:, joint, sensor] - base, upper[:, joint, sensor] - base, zoom)
            name, unit = _SENSORS[sensor]
            ax.set_title(f"joint {joint + 1} {name}", fontsize=10)
            ax.set_ylabel(("deviation " if relative else "") + f"[{unit}]")
            if row == len(sensors) - 1:
                ax.set_xlabel("time [s]")
    axes[0, 0].legend(fontsize=7, loc="best")
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    return fig


def plot_comparison(
    t,
    rmi_bounds,
    constant_bounds,
    *,
    y_meas=None,
    onset=None,
    alarms=None,
    joints=None,
    sensors=(0, 1),
    title=None,
    zoom=None,
):
    """RMI bands against constant thresholds, as deviations from the nominal output.

    Args:
        t: (T+1,) time in s.
        rmi_bounds, constant_bounds: :class:`~rmijax.methods.base.Bounds` (T+1, n, 2).
        y_meas: optional (T+1, n, 2) readings of a (faulty) run.
        onset: fault onset in s.
        alarms: optional ``{"RMI": time, "constant": time}`` first alarms to mark.
        zoom: as in :func:`plot_bands`, around the wider of the two bands.

    Returns:
        The matplotlib figure.
    """
    t = np.asarray(t)
    nominal = np.asarray(rmi_bounds.nominal)
    joints = list(range(nominal.shape[1]) if joints is None else joints)
    fig, axes = _axes_grid(len(joints), sensors)
    colours = {"RMI": "tab:blue", "constant": "tab:purple"}
    for col, joint in enumerate(joints):
        for row, sensor in enumerate(sensors):
            ax = axes[row, col]
            base = nominal[:, joint, sensor]
            ax.fill_between(
                t,
                np.asarray(rmi_bounds.lower)[:, joint, sensor] - base,
                np.asarray(rmi_bounds.upper)[:, joint, sensor] - base,
                color=colours["RMI"],
                alpha=0.25,
                lw=0,
                label="RMI band",
            )
            for edge in (constant_bounds.lower, constant_bounds.upper):
                ax.plot(
                    t,
                    np.asarray(edge)[:, joint, sensor] - base,
                    color=colours["constant"],
                    lw=1.0,
                    ls="-.",
                    label="constant threshold" if edge is constant_bounds.lower else None,
                )
            if y_meas is not None:
                ax.plot(
                    t,
                    np.asarray(y_meas)[:, joint, sensor] - base,
                    color="tab:green",
                    lw=0.9,
                    label="measured",
                )
            if onset is not None:
                ax.axvline(onset, color="k", ls="--", lw=0.8, label="fault onset")
            for name, when in (alarms or {}).items():
                if when is not None:
                    ax.axvline(
                        when,
                        color=colours.get(name, "tab:red"),
                        ls=":",
                        lw=1.4,
                        label=f"{name} alarm",
                    )
            edges = [
                np.asarray(b)[:, joint, sensor] - base
                for b in (
                    rmi_bounds.lower,
                    rmi_bounds.upper,
                    constant_bounds.lower,
                    constant_bounds.upper,
                )
            ]
            _zoom(ax, np.minimum(edges[0], edges[2]), np.maximum(edges[1], edges[3]), zoom)
            name, unit = _SENSORS[sensor]
            ax.set_title(f"joint {joint + 1} {name}", fontsize=10)
            ax.set_ylabel(f"deviation [{unit}]")
            if row == len(sensors) - 1:
                ax.set_xlabel("time [s]")
    axes[0, 0].legend(fontsize=7, loc="best")
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    return fig


def save_figure(fig, path, *, dpi=110):
    """Write ``fig`` as a PNG at ``path`` and close it. Returns the path."""
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path
