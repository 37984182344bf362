"""Faults and detection: the detector and its metrics, the fault suite, the online monitor.

- :mod:`~rmijax.detection.detect`: alarms, latency, false alarms, containment.
- :mod:`~rmijax.detection.suite`: the standard fault suite (every kind, every joint).
- :mod:`~rmijax.detection.monitor`: the online ``(init, update)`` monitor.

The faulty plant itself is part of the closed loop (:mod:`rmijax.plant`), since
band methods such as ``empirical`` and ``constant_corners`` run it too.
"""
