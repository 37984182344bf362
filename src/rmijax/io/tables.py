"""CSV and NPZ logs: one row (sample) per time stamp, one column per quantity and joint.

CSV header (any column order; names are case-sensitive)::

    time,q_d/joint1,qd_d/joint1,qdd_d/joint1,q/joint1,qd/joint1,q_d/joint2,...

``time`` in s; per joint the desired position ``q_d`` (rad), velocity ``qd_d``
(rad/s) and, optionally, acceleration ``qdd_d`` (rad/s^2), and the measured
position ``q`` (rad) and velocity ``qd`` (rad/s). An empty cell or ``nan`` is a
NaN sample. Other columns (``effort/joint1``, ...) and joints the robot does not
have are listed in ``Log.source["ignored"]``.

NPZ: arrays ``time`` (S,), ``joint_names`` (n,) strings, ``q_d``, ``qd_d``,
optional ``qdd_d``, ``q``, ``qd`` (S, n) in the ``joint_names`` order.
"""

from __future__ import annotations

import csv
import pathlib

import numpy as np

from rmijax.io.log import Log, LogError, assemble, joint_names, match_joints

__all__ = ["QUANTITIES", "read_csv", "read_npz", "write_csv", "write_npz"]

QUANTITIES = ("q_d", "qd_d", "qdd_d", "q", "qd")
"""Per-joint quantities of a CSV/NPZ log: desired position, velocity, acceleration; measured."""

_REQUIRED = ("q_d", "qd_d", "q", "qd")


def _cell(text):
    text = text.strip()
    return float(text) if text else np.nan


def _columns(path):
    with open(path, newline="") as handle:
        reader = csv.reader(handle)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise LogError(f"{path}: the file is empty (no header row)") from None
        rows = []
        for line, row in enumerate(reader, start=2):
            if not row or not any(v.strip() for v in row):
                continue
            if len(row) != len(header):
                raise LogError(
                    f"{path}: line {line} has {len(row)} cells but the header has {len(header)}"
                )
            try:
                rows.append([_cell(v) for v in row])
            except ValueError as err:
                raise LogError(f"{path}: line {line}: {err}") from None
    duplicates = sorted({h for h in header if header.count(h) > 1})
    if duplicates:
        raise LogError(f"{path}: column {duplicates[0]!r} appears more than once")
    data = np.asarray(rows, np.float64).reshape(len(rows), len(header))
    return header, data


def read_csv(path, params, **resample) -> Log:
    """Read a CSV log (module docstring) for robot ``params``; ``resample`` goes to
    :func:`rmijax.io.log.assemble` (``names``, ``dt``, ``kp``, ``kd``, ``reading_rule``, ...)."""
    path = pathlib.Path(path)
    header, data = _columns(path)
    if "time" not in header:
        raise LogError(f"{path}: no 'time' column (s); the header has {header[:8]}")
    per_joint, ignored = {}, []
    for index, name in enumerate(header):
        quantity, _, joint = name.partition("/")
        if name == "time":
            continue
        if quantity in QUANTITIES and joint:
            per_joint.setdefault(joint, {})[quantity] = index
        else:
            ignored.append(name)
    robot = resample.pop("names", None) or joint_names(params)
    _, extra = match_joints(list(per_joint), robot, str(path))
    missing = [f"{q}/{j}" for j in robot for q in _REQUIRED if q not in per_joint[j]]
    if missing:
        raise LogError(
            f"{path}: missing columns {missing}; each joint needs q_d/<joint>, qd_d/<joint>, "
            "q/<joint> and qd/<joint> (qdd_d/<joint> optional)"
        )
    with_accel = [j for j in robot if "qdd_d" in per_joint[j]]
    if with_accel and len(with_accel) != len(robot):
        lacking = [f"qdd_d/{j}" for j in robot if j not in with_accel]
        raise LogError(f"{path}: qdd_d is given for some joints only; missing {lacking}")
    ignored += [f"{q}/{j}" for j in extra for q in per_joint[j]]

    def take(quantity):
        return data[:, [per_joint[j][quantity] for j in robot]]

    time = data[:, header.index("time")]
    return assemble(
        params,
        reference_time=time,
        q_d=take("q_d"),
        qd_d=take("qd_d"),
        qdd_d=take("qdd_d") if with_accel else None,
        reading_time=time,
        q=take("q"),
        qd=take("qd"),
        source=dict(path=str(path), format="csv", ignored=ignored),
        names=robot,
        **resample,
    )


def read_npz(path, params, **resample) -> Log:
    """Read an NPZ log (module docstring) for robot ``params``; see :func:`read_csv`."""
    path = pathlib.Path(path)
    with np.load(path, allow_pickle=False) as archive:
        arrays = {key: archive[key] for key in archive.files}
    missing = [k for k in ("time", "joint_names", *_REQUIRED) if k not in arrays]
    if missing:
        raise LogError(
            f"{path}: missing arrays {missing}; an NPZ log holds time, joint_names, q_d, qd_d, "
            "q, qd (and optionally qdd_d)"
        )
    robot = resample.pop("names", None) or joint_names(params)
    order, extra = match_joints(arrays["joint_names"].tolist(), robot, str(path))
    n_log = len(arrays["joint_names"])
    columns = {}
    for key in QUANTITIES:
        if key not in arrays:
            continue
        value = np.asarray(arrays[key], np.float64)
        if value.ndim != 2 or value.shape != (arrays["time"].size, n_log):
            raise LogError(
                f"{path}: {key} must have shape (samples, joints) = "
                f"({arrays['time'].size}, {n_log}), got {value.shape}"
            )
        columns[key] = value[:, order]
    ignored = [k for k in arrays if k not in ("time", "joint_names", *QUANTITIES)]
    ignored += [f"joint {v}" for v in extra]
    return assemble(
        params,
        reference_time=arrays["time"],
        q_d=columns["q_d"],
        qd_d=columns["qd_d"],
        qdd_d=columns.get("qdd_d"),
        reading_time=arrays["time"],
        q=columns["q"],
        qd=columns["qd"],
        source=dict(path=str(path), format="npz", ignored=ignored),
        names=robot,
        **resample,
    )


def _log_values(q_d, qd_d, qdd_d, readings):
    readings = np.asarray(readings, np.float64)
    values = {
        "q_d": q_d,
        "qd_d": qd_d,
        "qdd_d": qdd_d,
        "q": readings[..., 0],
        "qd": readings[..., 1],
    }
    return {k: np.asarray(v, np.float64) for k, v in values.items() if v is not None}


def write_csv(path, *, time, joint_names, q_d, qd_d, readings, qdd_d=None):
    """Write a CSV log that :func:`read_csv` reads back.

    Args:
        time: (S,) s; joint_names: n names; q_d, qd_d, qdd_d (optional): (S, n);
        readings: (S, n, 2) measured encoder and tachometer.
    """
    values = _log_values(q_d, qd_d, qdd_d, readings)
    header, table = ["time"], [np.asarray(time, np.float64)]
    for j, name in enumerate(joint_names):
        for key in QUANTITIES:
            if key in values:
                header.append(f"{key}/{name}")
                table.append(values[key][:, j])
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        for row in np.stack(table, axis=-1):
            writer.writerow([repr(float(v)) for v in row])
    return pathlib.Path(path)


def write_npz(path, *, time, joint_names, q_d, qd_d, readings, qdd_d=None):
    """Write an NPZ log that :func:`read_npz` reads back (arguments as :func:`write_csv`)."""
    values = _log_values(q_d, qd_d, qdd_d, readings)
    time = np.asarray(time, np.float64)
    np.savez(path, time=time, joint_names=np.asarray(list(joint_names)), **values)
    return pathlib.Path(path)
