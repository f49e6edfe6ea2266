"""Counting XLA compilations, for the tests and the benchmarks that check none happens."""

from __future__ import annotations

from typing import ClassVar

import jax


class CompileCounter:
    """Counts XLA compilations while active: ``with CompileCounter() as c: ...; c.count``.

    Listens to JAX's ``/jax/core/compile/backend_compile_duration`` event (one per
    program handed to XLA), so cache hits do not count.
    """

    _active: ClassVar[list] = []
    _registered = False
    EVENT = "/jax/core/compile/backend_compile_duration"

    def __enter__(self) -> CompileCounter:
        if not CompileCounter._registered:
            jax.monitoring.register_event_duration_secs_listener(CompileCounter._listen)
            CompileCounter._registered = True
        self.count = 0
        CompileCounter._active.append(self)
        return self

    def __exit__(self, *exc) -> None:
        CompileCounter._active.remove(self)

    @staticmethod
    def _listen(event: str, duration: float, **kwargs) -> None:
        if event == CompileCounter.EVENT:
            for counter in CompileCounter._active:
                counter.count += 1
