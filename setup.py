"""Builds ``optax_bilateral._native``, the a-trous filter's C++ kernel (an XLA FFI handler).

Everything else about the package is in pyproject.toml. The extension is optional: where it
cannot be built (no C++17 compiler, no XLA FFI headers, another OS), the package installs
without it and the filter runs on its pure-JAX kernels, saying once why
(``optax_bilateral._src.filter.native``). The XLA FFI headers come from jaxlib
(``jax.ffi.include_dir()``), a build requirement. The code is compiled for the baseline of the
target (x86-64: SSE2) and, on x86-64, twice more with AVX2 and AVX-512 enabled per function;
the CPU's widest is chosen at run time (csrc/atrous.cc).
"""

import importlib.util
import os
import sys
from concurrent.futures import ThreadPoolExecutor

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext


def ffi_include_dir() -> str | None:
    """jaxlib's include folder, found without importing JAX (as ``jax.ffi.include_dir()``)."""
    spec = importlib.util.find_spec("jaxlib")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = os.path.join(next(iter(spec.submodule_search_locations)), "include")
    return path if os.path.isfile(os.path.join(path, "xla", "ffi", "api", "ffi.h")) else None


def native_extension() -> list[Extension]:
    include = ffi_include_dir()
    if include is None or sys.platform == "win32":
        print("optax_bilateral: no XLA FFI headers or no supported compiler: no native kernel")
        return []
    sources = [
        "module.cc",
        "atrous.cc",
        "count.cc",
        "isa.cc",
        "ldl.cc",
        "local.cc",
        "passes.cc",
        "stats.cc",
        "kernel_baseline.cc",
    ]
    if os.environ.get("OPTAX_BILATERAL_BASELINE_ONLY") != "1":
        sources += ["kernel_avx2.cc", "kernel_avx512.cc"]  # empty on other architectures
    flags = ["-std=c++17", "-O3", "-fno-math-errno", "-fno-trapping-math", "-fvisibility=hidden"]
    warnings = ["-Wall", "-Wextra", "-Wshadow", "-Wconversion", "-Wno-sign-conversion"]
    return [
        Extension(
            "optax_bilateral._native",
            sources=[os.path.join("csrc", s) for s in sources],
            # -isystem: warnings from XLA's own headers (jaxlib 0.11's api.h has one) are not ours.
            extra_compile_args=["-isystem", include, *flags, *warnings],
            extra_link_args=["-pthread"],
            language="c++",
            optional=True,
        )
    ]


class ParallelBuildExt(build_ext):
    """``build_ext`` that compiles an extension's sources on every core (distutils compiles
    them one after another; the three builds of the kernel are most of an install's time)."""

    def build_extension(self, ext):
        compile_one = self.compiler.compile

        def compile_all(sources, *args, **kwargs):
            with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
                parts = pool.map(lambda source: compile_one([source], *args, **kwargs), sources)
                return [obj for objects in parts for obj in objects]

        self.compiler.compile = compile_all
        try:
            super().build_extension(ext)
        finally:
            self.compiler.compile = compile_one


setup(ext_modules=native_extension(), cmdclass={"build_ext": ParallelBuildExt})
