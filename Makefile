# Set-up commands: `make demo`, `make test`, `make lint` and `make docs`. They create .venv on first use.
# `make test-min` and `make dist` make venvs of their own (.venv-min, build/dist-venv).
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python

.PHONY: demo test test-min lint docs dist install install-dev sanitize clean

# The native kernel (csrc/, built by setup.py inside every install below): a change to its
# sources reinstalls the package, which rebuilds it.
NATIVE_SOURCES := setup.py $(wildcard csrc/*.cc csrc/*.h)

# `make lint`: ruff (lint and format) on every Python source of the repository, pyright on
# the library (its settings in pyproject.toml).
LINT_PATHS := optax_bilateral tests experiments tools notebooks docs setup.py

# The venv's packages come through uv (installed into it by pip): it installs the ~150
# packages of the dev extras in a third of pip's time. It rebuilds the package each time
# (--reinstall-package): its cache knows pyproject.toml and setup.py, not csrc/.
UV_INSTALL = $(VENV)/bin/uv pip install --python $(PY) --quiet --reinstall-package optax_bilateral

$(VENV)/.installed: pyproject.toml $(NATIVE_SOURCES)
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet uv==0.13.9
	$(UV_INSTALL) -e ".[experiments]"
	touch $@

$(VENV)/.installed-dev: pyproject.toml $(NATIVE_SOURCES)
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet uv==0.13.9
	$(UV_INSTALL) -e ".[dev]"
	touch $(VENV)/.installed $@

install: $(VENV)/.installed
install-dev: $(VENV)/.installed-dev

demo: $(VENV)/.installed
	$(PY) -m experiments.paper.texture

# pytest exits 5 when it collects no tests; that must fail CI, and it does (non-zero).
# Two workers (the CI machine has 2 cores), a file per worker (module fixtures and the
# sharding tests' child process run once); hypothesis explores with its "ci" profile.
test: $(VENV)/.installed-dev
	OPTAX_BILATERAL_QUICK=1 HYPOTHESIS_PROFILE=ci $(PY) -m pytest -q -n 2 --dist loadfile --durations=25

# `make test-min`: the core tests (the filter, the transforms and bilateral_adam,
# checkpointing, the goldens to a tolerance) under the oldest versions pyproject.toml
# declares, pinned by constraints-min.txt, on the oldest Python it declares. Hypothesis's
# default profile: this run checks compatibility; `make test` explores.
PYTHON_MIN ?= python3.11
VENV_MIN := .venv-min
CORE_TESTS := tests/test_atrous.py tests/test_kernels.py tests/test_native.py tests/test_transforms.py \
	tests/test_rules.py tests/test_robustness.py tests/test_goldens.py

# The native kernel is compiled against the pinned jaxlib's own FFI headers: the build runs
# in this venv (--no-build-isolation), not in an isolated one with the newest jaxlib.
$(VENV_MIN)/.installed: pyproject.toml constraints-min.txt $(NATIVE_SOURCES)
	rm -rf $(VENV_MIN)
	$(PYTHON_MIN) -m venv $(VENV_MIN)
	$(VENV_MIN)/bin/python -m pip install --quiet --upgrade pip
	$(VENV_MIN)/bin/python -m pip install --quiet -c constraints-min.txt "setuptools>=77" jax jaxlib
	$(VENV_MIN)/bin/python -m pip install --quiet --no-build-isolation -c constraints-min.txt -e . \
		pytest pytest-xdist hypothesis optimistix
	touch $@

test-min: $(VENV_MIN)/.installed
	$(VENV_MIN)/bin/python -m pip check
	$(VENV_MIN)/bin/python tests/check_min_versions.py constraints-min.txt
	OPTAX_BILATERAL_QUICK=1 $(VENV_MIN)/bin/python -m pytest -q -n 2 --dist loadfile $(CORE_TESTS)

# `make dist`: the sdist and the wheel (python -m build) in dist/, checked by twine; then the
# wheel's contents (the library and its native kernel only); then the wheel in a clean venv
# outside the checkout (build/dist-venv): alone, it runs the README's
# quick start; with every extra, each gives what it promises (tests/check_dist.py).
# Nothing is uploaded (RELEASING.md).
DIST_VENV := build/dist-venv

dist: $(VENV)/.installed-dev
	rm -rf dist $(DIST_VENV)
	$(PY) -m build --outdir dist .
	$(VENV)/bin/twine check --strict dist/*
	$(PY) tests/check_dist.py wheel dist/*.whl
	$(PYTHON) -m venv $(DIST_VENV)
	$(DIST_VENV)/bin/python -m pip install --quiet --upgrade pip
	$(DIST_VENV)/bin/python -m pip install --quiet dist/*.whl
	cd $(DIST_VENV) && bin/python $(CURDIR)/tests/check_dist.py base
	$(DIST_VENV)/bin/python -m pip install --quiet "$$(ls dist/*.whl)[dev]"
	cd $(DIST_VENV) && bin/python $(CURDIR)/tests/check_dist.py extras

# `make sanitize`: the native kernels' C++ tests (csrc/test_atrous.cc: every grid rank, mode,
# mask and extreme against a float64 loop; csrc/test_ldl.cc: the mesh solves' LDL^T sweeps
# against dense float64 products; csrc/test_local.cc: the rules' sub-grid local averages against
# their tensor-product sum in float64; csrc/test_count.cc: the non-finite counts against
# std::isfinite on every 16-bit pattern and drawn float32/float64/complex blocks;
# csrc/test_stats.cc: the rules' texel statistics against their definition in float64) built with
# AddressSanitizer and UndefinedBehaviorSanitizer, any finding fatal, then run once per
# instruction set.
SANITIZE := -fsanitize=address,undefined -fno-sanitize-recover=all -fno-omit-frame-pointer
KERNELS := csrc/isa.cc csrc/passes.cc csrc/kernel_baseline.cc csrc/kernel_avx2.cc csrc/kernel_avx512.cc
sanitize:
	mkdir -p build
	for t in atrous ldl local count stats; do \
		uses=$$([ $$t = stats ] && echo csrc/local.cc); \
		$(CXX) -std=c++17 -O1 -g $(SANITIZE) -fno-math-errno -fno-trapping-math -Wall -Wextra \
			-Werror -Icsrc csrc/test_$$t.cc csrc/$$t.cc $$uses $(KERNELS) -pthread \
			-o build/test_$${t}_sanitized || exit 1; \
	done
	for isa in baseline avx2 avx512; do \
		for t in atrous ldl local count stats; do \
			OPTAX_BILATERAL_ISA=$$isa ASAN_OPTIONS=detect_leaks=1 build/test_$${t}_sanitized \
				|| exit 1; \
		done; \
	done

lint: $(VENV)/.installed-dev
	$(VENV)/bin/ruff check $(LINT_PATHS)
	$(VENV)/bin/ruff format --check $(LINT_PATHS)
	$(VENV)/bin/pyright optax_bilateral

# The docs site (mkdocs.yml) into site/; --strict: any warning (a broken link or anchor, a
# docstring griffe cannot parse) fails the build.
docs: $(VENV)/.installed-dev
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict

clean:
	rm -rf $(VENV) $(VENV_MIN) build dist results site .pytest_cache
