"""Offline tools around the segmenter: the ``gp-ground-seg`` command and what it is made of.

``cli`` is the entry point only (nothing imports it); ``errors`` (what bad input raises and how
it is shown) and ``options`` (options several subcommands share) serve every subcommand.
Scoring: ``evaluation`` (label ontologies, scoring protocols, metrics) and ``crossval``
(leave-one-group-out). Data: ``io`` (.bin, .label, .pcd) and ``bag`` (frames of bags and point
files, replay into a bag). Subcommands with a module of their own: ``batch`` (many inputs) on
``engine`` (in-process or Dask), ``tune`` (Optuna), ``play`` (play and hz on a live graph),
``plot`` (matplotlib). The optional extras (matplotlib, Dask, Optuna) are imported where they
are used; everything else at the top of each module, so the import graph has no cycle
(test/test_imports.py).
"""
