"""Evaluation: the worst-case judge and the comparison of band methods.

- :mod:`~rmijax.evaluation.worst_case`: gradient ascent over constant parameters.
- :mod:`~rmijax.evaluation.comparison`: scoring every method on one case.
"""
