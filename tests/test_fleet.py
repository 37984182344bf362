"""Fleet batches: sharded over 4 forced host devices they equal the single-device results."""

import dataclasses
import json
import os
import pathlib
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import rmijax
from rmijax import fleet

SRC = pathlib.Path(rmijax.__file__).parents[1]

_SCRIPT = textwrap.dedent(
    """
    import json
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    import rmijax
    from rmijax import fleet

    assert len(jax.devices()) == 4, jax.devices()
    params = getattr(rmijax, ROBOT)()
    paths = [("hold", "sine", 0.5), ("hold", "ramp", 0.3), ("slow_sine", "composite", 0.5),
             ("hold", "sine", 0.3), ("sine", "hold", 0.5)]
    trajs = [rmijax.trajectory([a, b][-params.n_joints:], duration=d) for a, b, d in paths]
    boxes = [params, params.with_box(hi=params.hi * 1.001), params, params, params]
    out = {"rmi": [], "rmi_sharded": [], "simulate": [], "certified": []}
    for traj, box, bounds in zip(trajs, boxes, fleet.rmi_batch(trajs, boxes)):
        ref = rmijax.rmi(traj, box)
        out["rmi"].append(max(float(np.max(np.abs(bounds.lower - ref.lower))),
                              float(np.max(np.abs(bounds.upper - ref.upper))),
                              float(np.max(np.abs(bounds.nominal - ref.nominal)))))
    for mode in ("coupled", "per_joint")[:params.n_joints]:
        ref = rmijax.rmi(trajs[0], params, mode=mode, window=20)
        got = fleet.rmi_sharded(trajs[0], params, mode=mode, window=20)  # 51 end steps on 4
        out["rmi_sharded"].append(float(np.max(np.abs(got.upper - ref.upper))
                                        + np.max(np.abs(got.lower - ref.lower))))
    certified = fleet.bounds_batch(trajs, boxes, method="certified") if CERTIFIED else []
    for traj, box, bounds in zip(trajs, boxes, certified):
        ref = rmijax.bounds(traj, box, method="certified")
        out["certified"].append(max(float(np.max(np.abs(bounds.lower - ref.lower))),
                                    float(np.max(np.abs(bounds.upper - ref.upper)))))
    th = rmijax.monte_carlo_parameters(params, 2, seed=1)[:5]
    last = params.n_joints - 1
    faults = [[rmijax.Fault("stuck_sensors", last, 0.2)], [], [rmijax.Fault("drift", 0, 0.1, 0.1)],
              [rmijax.Fault("locked", last, 0.2)], []]
    xs, ys = fleet.simulate_batch(trajs, params, th, faults=faults)
    for r in range(5):
        x, y = rmijax.simulate(trajs[r], params, th[r], faults=faults[r])
        assert xs[r].shape == x.shape
        out["simulate"].append(float(max(np.max(np.abs(xs[r] - x)), np.max(np.abs(ys[r] - y)))))
    print("RESULT", json.dumps(out))
    """
)


@pytest.mark.parametrize(
    "robot, certified",
    [
        ("paper_pendulum", False),
        pytest.param("paper_pendulum", True, marks=pytest.mark.slow),
        pytest.param("paper_arm2", False, marks=pytest.mark.slow),
    ],
)
def test_sharded_equals_single_device_on_4_host_devices(robot, certified):
    """rmi and certified over 5 runs of 2 lengths and 2 boxes (5 on 4 devices: uneven), rmi
    over the 51 end steps of one run (both modes on the arm), simulate with faults: all
    within 1e-12 of one device."""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4")
    env["PYTHONPATH"] = os.pathsep.join([str(SRC), env.get("PYTHONPATH", "")])
    script = f"ROBOT = {robot!r}\nCERTIFIED = {certified}\n" + _SCRIPT
    done = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=900
    )
    assert done.returncode == 0, done.stderr[-3000:]
    line = next(v for v in done.stdout.splitlines() if v.startswith("RESULT "))
    result = json.loads(line[len("RESULT ") :])
    assert len(result["rmi"]) == len(result["simulate"]) == 5
    assert len(result["certified"]) == (5 if certified else 0)
    for key, errors in result.items():
        assert max(errors, default=0.0) <= 1e-12, (key, errors)


def test_batch_on_one_device_broadcasts_and_checks():
    params = rmijax.paper_pendulum()
    trajs = [rmijax.trajectory("sine", duration=d) for d in (0.3, 0.2)]
    compiled = fleet._program.cache_info().misses
    got = fleet.bounds_batch(trajs, params, method="rmi", window=10)
    again = fleet.rmi_batch(trajs[::-1], params, window=10)  # same shapes: no new program
    assert fleet._program.cache_info().misses == compiled + 1
    np.testing.assert_array_equal(again[0].upper[:21], got[1].upper)
    assert [b.lower.shape for b in got] == [(31, 1, 2), (21, 1, 2)]
    ref = rmijax.rmi(trajs[1], params, window=10)
    np.testing.assert_allclose(got[1].upper, ref.upper, atol=1e-12)
    with pytest.raises(ValueError, match="batch sizes differ"):
        fleet.rmi_batch(trajs, [params] * 3)
    with pytest.raises(TypeError, match="trajs must be a Trajectory"):
        fleet.rmi_batch([], params)
    other = rmijax.trajectory("sine", duration=0.2, dt=0.005)
    with pytest.raises(ValueError, match="different steps dt"):
        fleet.rmi_batch([trajs[0], other], params, window=10)
    x, y = fleet.simulate_batch(trajs[0], params, np.asarray(params.nominal))
    assert len(x) == 1 and x[0].shape == (31, 1, 2)
    short = fleet.bounds_batch(trajs, params, method="short_window", readings=[y[0], y[0][:21]])
    np.testing.assert_allclose(
        short[1].upper,
        rmijax.bounds(trajs[1], params, method="short_window", readings=y[0][:21]).upper,
        atol=1e-12,
    )
    assert fleet.device_mesh(1).size == 1
    assert fleet.my_share(range(5)) == list(range(5))


_TWO_HOSTS = textwrap.dedent(
    """
    import sys
    import jax
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(sys.argv[1], num_processes=2, process_id=int(sys.argv[2]))
    import numpy as np
    import rmijax
    from rmijax import fleet

    assert jax.process_count() == 2 and len(jax.devices()) == 4, jax.devices()
    params = rmijax.paper_pendulum()
    trajs = [rmijax.trajectory("sine", duration=d) for d in (0.3, 0.2, 0.3)]
    errors = [
        float(np.max(np.abs(b.upper - rmijax.rmi(t, params, window=10).upper)))
        for t, b in zip(trajs, fleet.rmi_batch(trajs, params, window=10))
    ]
    print("ERROR", max(errors), flush=True)
    """
)


def _free_port():
    import socket

    with socket.socket() as probe:
        probe.bind(("localhost", 0))
        return probe.getsockname()[1]


@pytest.mark.slow
def test_two_processes_share_one_mesh():
    """jax.distributed.initialize with 2 local processes x 2 host devices: one 4-device mesh,
    every process gets the whole result, equal to one device."""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    env["PYTHONPATH"] = os.pathsep.join([str(SRC), env.get("PYTHONPATH", "")])
    address = f"localhost:{_free_port()}"
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", _TWO_HOSTS, address, str(rank)],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for rank in range(2)
    ]
    outputs = [p.communicate(timeout=600) for p in procs]
    for proc, (out, err) in zip(procs, outputs, strict=True):
        assert proc.returncode == 0, err[-3000:]
        line = next(v for v in out.splitlines() if v.startswith("ERROR "))
        assert float(line.split()[1]) <= 1e-12


def test_certified_batch_passes_the_enclosure_and_propagation_on():
    """``certified_batch`` with the affine/carried pair equals the single-run call (and so
    differs from the interval/kernel default)."""
    params = rmijax.paper_pendulum()
    traj = rmijax.trajectory(["sine"], duration=0.3)
    options = dict(splits=2, enclosure="affine", propagate="carried")
    (batch,) = fleet.certified_batch([traj], [params], **options)
    single = rmijax.certified_bounds(traj, params, **options)[0]
    np.testing.assert_allclose(batch.upper, single.upper, rtol=0, atol=1e-15)
    np.testing.assert_allclose(batch.lower, single.lower, rtol=0, atol=1e-15)
    (default,) = fleet.certified_batch([traj], [params], splits=2)
    assert np.max(np.asarray(default.width) - np.asarray(batch.width)) > 0


def test_certified_batch_on_a_loaded_chain_equals_the_single_run_call(tmp_path):
    """Two runs of the two-joint URDF arm carrying a payload (40 and 24 steps of
    ``hold``/``sine``; payload 0-0.5 kg, and one box with the payload certain at 0.25 kg
    plus Coulomb ranges 0-10 N m): with the default ``coulomb="auto"`` the batch equals
    ``certified_bounds`` per run, whether the certain parameters are folded (both boxes
    alike) or not (boxes differ in what is certain). On the Coulomb box ``"auto"`` takes
    the sign's range on some steps and expands it on others, so both branches run through
    the batch. A load with another parameter layout is refused; another load with the
    same layout is the same model and runs alike. The chain model and the folding are
    those of a 6-joint arm; on the UR5e this test took 517 s of a CI run (the 6-joint
    batches' compiles), on two joints it checks the same equalities."""
    from arm2_urdf import arm2_urdf

    path = tmp_path / "arm2.urdf"
    path.write_text(arm2_urdf())
    traj = rmijax.trajectory(["hold", "sine"], duration=0.4)
    keys = ("t", "q_d", "qd_d", "qdd_d", "u_d", "x_n", "qdd_n")
    short = [
        dataclasses.replace(traj, **{k: getattr(traj, k)[: s + 1] for k in keys}) for s in (40, 24)
    ]
    payload = rmijax.load_robot(path, payload=(0.0, 0.5), friction=dict(coulomb=(0.0, 0.0)))
    lo, hi = np.asarray(payload.lo), np.asarray(payload.hi)
    assert lo.size == 5  # two mass scales (certain), the payload, two Coulomb levels
    friction = payload.with_box(
        lo=np.r_[lo[:2], 0.25, lo[3:]], hi=np.r_[hi[:2], 0.25, hi[3:] + 10.0]
    )
    batches = []
    for robots in ([payload, payload], [payload, friction]):
        batch = fleet.certified_batch(short, robots)
        batches.append(batch)
        for t, r, got in zip(short, robots, batch, strict=True):
            want, cert = rmijax.certified_bounds(t, r)
            assert cert.coulomb == "auto"
            assert got.upper.shape == (t.n_steps + 1, 2, 2)
            assert np.all(np.isfinite(got.upper - got.lower))
            np.testing.assert_allclose(got.upper, want.upper, rtol=1e-13, atol=1e-15)
            np.testing.assert_allclose(got.lower, want.lower, rtol=1e-13, atol=1e-15)
    keep = np.asarray(cert.keep)  # the Coulomb box's run: both choices made
    assert np.any(keep == 0) and np.any(keep == 1)
    with pytest.raises(ValueError, match=r"params\[1\].*layout.*with_box"):
        fleet.certified_batch(short, [payload, rmijax.load_robot(path, payload=(0.0, 0.5))])
    # a second load with the same layout is the same model
    again = rmijax.load_robot(path, payload=(0.0, 0.5), friction=dict(coulomb=(0.0, 0.0)))
    for got, want in zip(fleet.certified_batch(short, [payload, again]), batches[0], strict=True):
        np.testing.assert_array_equal(got.upper, want.upper)


def test_certified_batch_bounds_coulomb_by_range(tmp_path):
    """``coulomb="range"`` reaches the batch: two runs of the two-joint URDF arm with
    Coulomb ranges (20 and 12 steps of ``hold``/``sine``) equal the single-run call with
    it, and differ from the Taylor sign's bands."""
    from arm2_urdf import arm2_urdf

    path = tmp_path / "arm2.urdf"
    path.write_text(arm2_urdf())
    params = rmijax.load_robot(path, mass=0.05, friction=dict(coulomb=(0.0, 10.0)))
    traj = rmijax.trajectory(["hold", "sine"], duration=0.2)
    keys = ("t", "q_d", "qd_d", "qdd_d", "u_d", "x_n", "qdd_n")
    runs = [
        dataclasses.replace(traj, **{k: getattr(traj, k)[: s + 1] for k in keys}) for s in (20, 12)
    ]
    batch = fleet.certified_batch(runs, params, coulomb="range")
    for run, got in zip(runs, batch, strict=True):
        want = rmijax.certified_bounds(run, params, coulomb="range")[0]
        np.testing.assert_allclose(got.upper, want.upper, rtol=1e-13, atol=1e-15)
        np.testing.assert_allclose(got.lower, want.lower, rtol=1e-13, atol=1e-15)
        taylor = rmijax.certified_bounds(run, params, coulomb="taylor")[0]
        assert not np.allclose(got.upper, taylor.upper, rtol=1e-9, atol=0)
