"""The tuning benchmark's problem type, :class:`Scene` (see :mod:`experiments.tuning.scenes`),
and the first learning-rate grid :func:`around`: apart from the scenes, so that the modules
that build scenes (:mod:`~experiments.tuning.scenes`, :mod:`~experiments.tuning.camera_distance`)
share them without importing each other."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax

Params = Any


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """One inverse problem of the benchmark (:mod:`experiments.tuning.scenes` says more).

    Attributes:
      name: short identifier (``SCENES`` key).
      description: one line for tables and plots.
      init: the starting parameters (a pytree of arrays).
      data: arrays the functions below read (targets, reference images, ...).
      grad: ``(data, params, key) -> grads``, a noisy unbiased gradient.
      project: ``(data, params) -> params`` in the valid domain.
      error: ``(data, params) -> scalar`` parameter error.
      iterations: steps of every run.
      learning_rates: the first learning-rate grid of every method (the benchmark
        extends it where the best value lies at an edge).
      scale: the parameters' unit: the ``sigma_d`` grid of a linear guide is
        multiplied by it (1 for unit-range parameters).
      log_guide: the parameters are positive and span decades; the grid then also
        covers ``log_guide=True`` (as the paper's texture runs).
      error_name: what ``error`` measures, for tables.
      config: JSON-able settings that identify the problem (the cache key).
      spatial_axes: the parameters' spatial axes, passed to every filtered method, where
        the library's default leaf rule would not filter them (a 1-D (N, 1) signal).
      batch: runs advanced together (their gradients in one vmapped program).
    """

    name: str
    description: str
    init: Params
    data: Any
    grad: Callable[[Any, Params, jax.Array], Params]
    project: Callable[[Any, Params], Params]
    error: Callable[[Any, Params], jax.Array]
    iterations: int
    learning_rates: tuple[float, ...]
    scale: float = 1.0
    log_guide: bool = False
    error_name: str = "mean |theta - theta_target|"
    config: dict = dataclasses.field(default_factory=dict)
    batch: int = 24
    spatial_axes: Any = None

    def initial_error(self) -> float:
        return float(self.error(self.data, self.init))


def around(lr: float) -> tuple[float, ...]:
    """The first learning-rate grid: ``lr`` and a factor of 2 either side (the benchmark
    extends it by factors of 2 where the best value lies at an edge)."""
    return (lr / 2, lr, 2 * lr)
