"""Robots: the model interface, the parameter box and its corners, and the arms.

- :mod:`~rmijax.robots.model`: :class:`RobotModel`, ``M(q, th)`` and ``h(q, qd, th)``.
- :mod:`~rmijax.robots.structure`: what a model declares about its parameters.
- :mod:`~rmijax.robots.box`: :class:`UncertainRobot`, the box ``[lo, hi]`` and its corners.
- :mod:`~rmijax.robots.planar`: the paper's planar point-mass arm and its presets.
- :mod:`~rmijax.robots.spatial`: rigid-body dynamics of serial chains (real 6-7 joint arms).
- :mod:`~rmijax.robots.loaders`: ``load_robot`` from URDF, MJCF or a shipped arm
  (``descriptions/``: Panda, iiwa14, UR5e, mesh-free MJCF from MuJoCo Menagerie).
"""
