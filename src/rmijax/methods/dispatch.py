"""One interface to every bound method: ``rmijax.bounds(traj, params, method=...)``.

Every method returns :class:`~rmijax.methods.base.Bounds` shaped like :func:`rmijax.rmi`'s
(``lower``, ``upper``, ``nominal``, ``crossed``: (T+1, n, 2)), so detection,
plots and the comparison treat them alike. The definitions are in
``docs/methods.md``; in short:

- ``rmi``: exact RMI, all corners (the paper's algorithm, SPEC section 5).
- ``empirical``: the paper's constant thresholds from fault-free runs.
- ``short_window``: RMI over a few steps (default 2) from the *measured*
  state; needs ``readings``.
- ``corner_search``: RMI with the extreme corner searched (gradient sign, then
  single-bit flips) instead of enumerated; cost polynomial in the links.
- ``constant_corners``: the envelope of the closed loop run once per corner
  held constant (the physical robot has constant parameters).
- ``linearized``: first-order parameter sensitivity of the windowed closed
  loop, plus a remainder margin; cost polynomial in the links.
- ``certified``: a band proven to contain every constant-parameter run (a
  Taylor model with a rigorous remainder); the certificate comes from
  :func:`rmijax.certified.certified_bounds`.
"""

from __future__ import annotations

import inspect

from rmijax.methods.base import Bounds
from rmijax.methods.certified import certified_bounds
from rmijax.methods.constant_corners import constant_corner_bounds
from rmijax.methods.corner_search import corner_search_bounds
from rmijax.methods.empirical import empirical_thresholds
from rmijax.methods.linearized import linearized_bounds
from rmijax.methods.rmi import rmi
from rmijax.methods.short_window import short_window_bounds
from rmijax.robots.box import UncertainRobot
from rmijax.trajectory import Trajectory

__all__ = ["DEFAULT_WINDOWS", "METHODS", "SCALABLE_METHODS", "bounds", "options_of"]

METHODS = (
    "rmi",
    "empirical",
    "short_window",
    "corner_search",
    "constant_corners",
    "linearized",
    "certified",
)
"""Names accepted by :func:`bounds`."""

SCALABLE_METHODS = ("empirical", "corner_search", "linearized")
"""Methods whose cost does not grow like ``2^p`` (the comparison ran them at 16 links)."""

DEFAULT_WINDOWS = {
    "rmi": 100,
    "short_window": 2,
    "corner_search": 100,
    "constant_corners": 100,
    "linearized": 100,
}
"""The window ``N`` (steps) each method uses when ``window`` is not given."""


_FUNCTIONS = {
    "rmi": rmi,
    "empirical": empirical_thresholds,
    "short_window": short_window_bounds,
    "corner_search": corner_search_bounds,
    "constant_corners": constant_corner_bounds,
    "linearized": linearized_bounds,
    "certified": certified_bounds,
}
_COMMON = {"mode", "window", "noise_lo", "noise_hi", "readings", "remainder_scale"}


def options_of(method: str) -> tuple[str, ...]:
    """The extra keyword options ``method`` takes through :func:`bounds`."""
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {METHODS}")
    signature = inspect.signature(_FUNCTIONS[method])
    return tuple(
        name
        for name, p in signature.parameters.items()
        if p.kind is inspect.Parameter.KEYWORD_ONLY and name not in _COMMON
    )


def bounds(
    traj: Trajectory,
    params: UncertainRobot,
    *,
    method: str = "rmi",
    mode: str = "coupled",
    window: int | None = None,
    noise_lo=0.0,
    noise_hi=0.0,
    readings=None,
    **options,
) -> Bounds:
    """Bounds of every output at every step, by one of :data:`METHODS`.

    Args:
        traj: the desired motion and its nominal response.
        params: the robot and its parameter box.
        method: one of :data:`METHODS` (``docs/methods.md`` defines them).
        mode: ``"coupled"`` or ``"per_joint"`` for the RMI-type methods
            (``rmi``, ``short_window``, ``corner_search``); the methods that
            simulate the true plant (``constant_corners``, ``linearized``) and
            ``empirical`` take ``"coupled"`` only.
        window: ``N`` in steps; default per method (:data:`DEFAULT_WINDOWS`).
            ``empirical`` has none; ``constant_corners`` uses it only with
            ``horizon="window"``.
        noise_lo, noise_hi: sensor noise bounds, scalar, (2,) or (n, 2).
        readings: (T+1, n, 2) measured outputs; required by ``short_window``
            (its windows start from them), refused by the others.
        **options: passed to the method's function: ``rmi``
            (:func:`rmijax.rmi`), ``empirical``
            (:func:`rmijax.empirical_thresholds`: ``runs``, ``safety``,
            ``seed``), ``short_window`` (``start``), ``corner_search``
            (``max_rounds``), ``constant_corners`` (``horizon``),
            ``linearized`` (``margin``), ``certified`` (``splits``,
            ``segments``, ``kernel_steps``), and the batching options
            ``chunk_size``, ``progress``.

    Returns:
        :class:`~rmijax.methods.base.Bounds`, each field (T+1, n, 2).

    Raises:
        ValueError: an unknown method, or an argument the method does not take
            (``readings`` for a model-only method, ``window`` for ``empirical``,
            ``per_joint`` for a method of the true plant).
        TypeError: an option the method does not have (the message lists its
            options, see :func:`options_of`).
    """
    allowed = options_of(method)
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise TypeError(
            f"method={method!r} takes no option {unknown[0]!r}; its options are {allowed}"
        )
    if readings is not None and method != "short_window":
        raise ValueError(
            f"readings are used by method='short_window' only; method={method!r} "
            "computes its bounds from the model alone"
        )
    noise = dict(noise_lo=noise_lo, noise_hi=noise_hi)
    if method == "empirical":
        if window is not None:
            raise ValueError("method='empirical' has no window: its band is constant")
        _coupled_only(method, mode)
        return empirical_thresholds(traj, params, **noise, **options)
    if method == "certified":
        if window is not None:
            raise ValueError("method='certified' has no window: it certifies the whole run")
        _coupled_only(method, mode)
        return certified_bounds(traj, params, **noise, **options)[0]
    window = DEFAULT_WINDOWS[method] if window is None else window
    if method == "rmi":
        return rmi(traj, params, mode=mode, window=window, **noise, **options)
    if method == "short_window":
        return short_window_bounds(
            traj, params, readings, mode=mode, window=window, **noise, **options
        )
    if method == "corner_search":
        return corner_search_bounds(traj, params, mode=mode, window=window, **noise, **options)
    _coupled_only(method, mode)
    if method == "constant_corners":
        return constant_corner_bounds(traj, params, window=window, **noise, **options)
    return linearized_bounds(traj, params, mode=mode, window=window, **noise, **options)


def _coupled_only(method, mode):
    if mode != "coupled":
        raise ValueError(
            f"method={method!r} describes the true coupled plant; mode must be 'coupled', "
            f"got {mode!r} (per_joint is an RMI simplification)"
        )
