"""Applications: the paper's experiments, figures and the command line.

- :mod:`~rmijax.apps.experiments`: the paper's runs, fault tables, containment.
- :mod:`~rmijax.apps.plotting`: figures shared by the CLI and the notebooks.
- :mod:`~rmijax.apps.cli`: ``rmijax --out DIR``.
"""
