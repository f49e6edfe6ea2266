"""Tuning benchmark (issue #17): how much of the filter's gain survives without per-problem tuning.

    python -m experiments.tuning [--quick] [--out DIR] [--only-scenes a,b] [--jobs N]
                                 [--candidates [NAME=]module:factory,...] [--recompute]
                                 [--reference FILE]

For every scene of :mod:`experiments.tuning.scenes` (texture, its noise target, its
low-noise variant, volume, a 1-D signal, deblurring, deblurring at 100x scale)
it reports the final parameter error (median over seeds) of

* ``best_tuned``: ``bilateral_adam`` (postfilter, ``b1 = 0.2``) at the best point of a
  grid over ``sigma_d`` (0, 1e-3 ... 3, inf; times the scene's parameter unit for a
  linear guide), ``levels`` 2..6, ``log_guide`` (scenes with positive parameters
  spanning decades) and the learning rate;
* ``auto``: ``bilateral_adam(learning_rate, sigma_d="auto")``, learning rate swept
  (only when the installed library accepts ``sigma_d="auto"``; otherwise the row
  says "not available");
* ``defaults``: ``bilateral_adam(learning_rate)`` (its default ``sigma_d``, ``levels``),
  learning rate swept;
* ``adam``: ``optax.adam``, learning rate, ``b1`` and ``b2`` (0.999 or ``1 - (1 - b1)^2``) swept;
* ``pyramid``: Weier et al.'s Laplacian-pyramid parameterisation optimised with Adam
  (:func:`optax_bilateral.pyramid_adam`), learning rate and pyramid levels swept;
* any ``--candidates``: learning rate swept.

Every learning-rate sweep starts from the scene's grid (factor 2 apart) and is
extended by one factor of 2 at an edge where the best value lies, up to three
times, so the optimum is inside the grid (``summary.json`` flags points where it
is still at an edge).

Plugging in a candidate (the API the ``sigma_d="auto"`` work uses)
--------------------------------------------------------------------
A *candidate* is a factory ``factory(learning_rate) -> optax.GradientTransformation``
(``learning_rate`` arrives as a traced scalar, so one compiled update program serves
every learning rate and seed). A factory with a ``scene`` parameter also receives the
:class:`experiments.tuning.scenes.Scene` (e.g. to use ``log_guide`` where ``scene.log_guide``).
From the command line (``module`` importable, e.g. a file on ``PYTHONPATH``)::

    python -m experiments.tuning --only-scenes deblur,texture --candidates auto2=mymodule:factory

compares it with the stored grid (``--out``'s ``cache/``; the grid is only run when
its cache is missing or its configuration changed) and adds it to ``table.md``
with its ratios to the best-tuned and to Adam's error. From Python::

    from experiments import tuning
    from experiments.tuning import scenes
    scene = scenes.make("deblur")
    factory = lambda learning_rate, sigma_d: ob.bilateral_adam(learning_rate, sigma_d=sigma_d)
    settings = [{"learning_rate": 0.02, "sigma_d": s} for s in (0.02, 0.1)]
    errors = tuning.evaluate(scene, factory, settings, seeds=(0, 1, 2))  # (2, 3) final errors
    result = tuning.tune(scene, tuning.Family("mine", factory))   # learning rate swept
    result.best.median, result.best.hyper

:func:`run_benchmark` runs the whole table (``candidates={"name": factory}``).

Without the grids: ``--reference``
----------------------------------
The grids take about 17 minutes on two cores; a candidate's own learning-rate sweep
one or two. Every run writes ``reference.json`` (per scene and grid family: a key of the
scene's and the grid's configuration, and each setting's record at its best learning
rate), and ``--reference FILE`` takes the best-tuned, Adam and pyramid grids from such a
file instead of running them (``auto``, the defaults and the candidates still run). The
repository keeps the full run's file, so on a fresh clone::

    python -m experiments.tuning --reference experiments/tuning/reference.json \
        --candidates mine=mymodule:factory --out results/mine

A file of another setting (``--quick`` or not), without a requested scene, or whose
scene, grid or settings no longer match this code's is refused with the reason: rerun
the grids and commit that run's ``reference.json``. The table names the file and the
library version that ran its grids.

Cost: every scene compiles its noisy gradient once (``jax.vmap`` over a batch of
runs: every run of every method advances together) and one update program per
method and static setting (``levels``, ``log_guide``); the runs of a batch differ
in traced hyperparameters and seeds and go through ``jax.lax.map`` in the update
(sequential runs: the filter's ``lax.cond`` stays a branch; under ``vmap`` it
would run both branches). ``summary.json`` records each scene's and family's
seconds.

Outputs in ``--out`` (default ``results/tuning``): ``summary.json`` (per scene:
every method's median error, its hyperparameters and per-seed errors, and the
whole grid), ``table.md``, ``reference.json`` (above), ``<scene>.png`` (final error
against ``sigma_d``, one curve per ``levels`` at that point's best learning rate,
``auto`` / Adam / pyramid as horizontal lines; 0 and inf at the ends of the log axis)
and ``cache/``.

The package, by job: :mod:`~experiments.tuning.scenes` (the problems; the Mitsuba ones in
:mod:`~experiments.tuning.camera_distance`; their type, :class:`Scene`, in
:mod:`~experiments.tuning.problem`), :mod:`~experiments.tuning.sweep` (running a method,
the learning-rate sweep), :mod:`~experiments.tuning.methods` (the methods compared, their
grids), :mod:`~experiments.tuning.store` (the cache and reference files),
:mod:`~experiments.tuning.report` (plots, ``table.md``) and
:mod:`~experiments.tuning.benchmark` (every method on every scene, the command line).
The names below are its API, as docs/tuning.md uses it.
"""

from experiments.tuning.benchmark import load_candidates, main, run_benchmark, run_scene
from experiments.tuning.methods import (
    REDUCED,
    Settings,
    adam_factory,
    auto_factory,
    bilateral_factory,
    defaults_factory,
    families,
    pyramid_factory,
    settings,
    sparse_factory,
    sure_factory,
)
from experiments.tuning.report import markdown, plot_scene, sensitivity
from experiments.tuning.store import REFERENCE_FAMILIES, load_reference
from experiments.tuning.sweep import Family, Record, Result, Runner, evaluate, tune

__all__ = [
    "REDUCED",
    "REFERENCE_FAMILIES",
    "Family",
    "Record",
    "Result",
    "Runner",
    "Settings",
    "adam_factory",
    "auto_factory",
    "bilateral_factory",
    "defaults_factory",
    "evaluate",
    "families",
    "load_candidates",
    "load_reference",
    "main",
    "markdown",
    "plot_scene",
    "pyramid_factory",
    "run_benchmark",
    "run_scene",
    "sensitivity",
    "settings",
    "sparse_factory",
    "sure_factory",
    "tune",
]
