"""Shared builders for the tests: random boxes and gains."""

from __future__ import annotations

import importlib.util
import pathlib

import numpy as np

import rmijax


def random_arm(rng, n, *, certain=()):
    """A planar arm with a random asymmetric box around random nominal values."""
    masses = rng.uniform(2.0, 12.0, n)
    lengths = rng.uniform(0.5, 1.5, n)
    nominal = np.concatenate([masses, lengths])
    below = nominal * rng.uniform(0.01, 0.12, 2 * n)
    above = nominal * rng.uniform(0.01, 0.12, 2 * n)
    lo, hi = nominal - below, nominal + above
    for b in certain:
        lo[b] = hi[b] = nominal[b]
    return rmijax.planar_arm(nominal, lo, hi)


def random_gains(rng, n):
    kp = rng.uniform(40.0, 160.0, n)
    kd = rng.uniform(12.0, 30.0, n)
    return kp, kd


ROOT = pathlib.Path(__file__).resolve().parent.parent


def load_benchmark(name):
    """The script ``benchmarks/<name>.py`` as a module (its ``main`` is not run)."""
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def jets_at_a_point(function, arrays, noise=None, precond=None):
    """Evaluate perturbation jets (``planar_perturbation_jets`` or a chain's) at a point,
    in the certificate checker's mpmath intervals: ``arrays`` = ``q, qd, th, nominal, u,
    kp, kd`` (float arrays), ``noise`` None or (n, 2), ``precond`` None or (n, n).

    Returns:
        ``(lower, upper)``: float arrays of ``gv``'s enclosure, (n,).
    """
    from rmijax._intervals import Jet
    from rmijax.methods.certificate_check import _iv, _MpBackend

    iv = _iv()
    backend = _MpBackend(iv)
    zero = iv.mpf(0)

    def jets(values):
        grad, hess = np.full(1, zero, dtype=object), np.full((1, 1), zero, dtype=object)
        return [Jet(iv.mpf(float(v)), grad, hess, backend) for v in np.asarray(values)]

    extra = None if noise is None else (jets(noise[:, 0]), jets(noise[:, 1]))
    matrix = None if precond is None else [jets(row) for row in precond]
    gv = function(*(jets(a) for a in arrays), extra, matrix)
    return np.array([float(g.v.a) for g in gv]), np.array([float(g.v.b) for g in gv])
