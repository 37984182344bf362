"""Band methods: every way rmijax bounds the readings of a healthy robot.

- :mod:`~rmijax.methods.dispatch`: ``rmijax.bounds(traj, params, method=...)``.
- :mod:`~rmijax.methods.base`: :class:`Bounds` and the errors every method shares.
- :mod:`~rmijax.methods.rmi`: exact RMI (the engine); its corner searches in
  :mod:`~rmijax.methods.choosers` (enumeration and the structured searches),
  :mod:`~rmijax.methods.planar_search` (the planar arm's factored search) and
  :mod:`~rmijax.methods.linear_search` (real arms: ``LinearDynamics`` window steps).
- One file per other method: :mod:`~rmijax.methods.empirical`,
  :mod:`~rmijax.methods.short_window`, :mod:`~rmijax.methods.corner_search`,
  :mod:`~rmijax.methods.constant_corners`, :mod:`~rmijax.methods.linearized`.
"""
