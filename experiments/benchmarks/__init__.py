"""Benchmarks: what the filter costs, what it buys and how it scales (BENCHMARKS.md).

``python -m experiments.benchmarks`` runs the suite (:mod:`~experiments.benchmarks.suite`);
``native``, ``gpu`` and ``sharding`` time the kernels and the split grids. ``compiles`` and
``collectives`` are the instruments they measure with (XLA compilations, the bytes an SPMD
program moves); they import only JAX and NumPy, so the library's tests use them too.
"""
