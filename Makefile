# Set-up commands: `make demo`, `make test`, `make lint` and `make docs`. They create .venv on first use.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python

.PHONY: demo test lint docs install install-dev clean

# The paths `make lint` checks (ruff lint + format, pyright): the library (but the
# Mitsuba and pyramid modules) and the tests written to its standards.
# Extend as other files are brought up to them.
LINT_PATHS := \
	optax_bilateral/__init__.py \
	optax_bilateral/_src/alias.py \
	optax_bilateral/_src/atrous.py \
	optax_bilateral/_src/bilateral.py \
	optax_bilateral/_src/filter.py \
	optax_bilateral/_src/layout.py \
	optax_bilateral/_src/leaves.py \
	optax_bilateral/_src/triangle_mesh.py \
	optax_bilateral/_src/numerics.py \
	optax_bilateral/_src/sharded.py \
	optax_bilateral/_src/state_io.py \
	optax_bilateral/_src/step.py \
	optax_bilateral/_src/transforms.py \
	optax_bilateral/_src/validation.py \
	optax_bilateral/toy/__init__.py \
	optax_bilateral/toy/texture.py \
	optax_bilateral/toy/volume.py \
	experiments/collectives.py \
	tests/conftest.py \
	tests/goldens.py \
	tests/snapshots.py \
	tests/reference.py \
	tests/test_atrous.py \
	tests/test_authors.py \
	tests/test_goldens.py \
	tests/test_packaging.py \
	tests/test_properties.py \
	tests/test_robustness.py \
	tests/test_snapshots.py \
	tests/test_transforms.py
TYPECHECK_PATHS := $(filter optax_bilateral/%,$(LINT_PATHS))

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[experiments]"
	touch $@

$(VENV)/.installed-dev: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[dev]"
	touch $(VENV)/.installed $@

install: $(VENV)/.installed
install-dev: $(VENV)/.installed-dev

demo: $(VENV)/.installed
	$(PY) -m experiments.texture

# pytest exits 5 when it collects no tests; that must fail CI, and it does (non-zero).
# Two workers (the CI machine has 2 cores), a file per worker (module fixtures and the
# sharding tests' child process run once); hypothesis explores with its "ci" profile.
test: $(VENV)/.installed-dev
	OPTAX_BILATERAL_QUICK=1 HYPOTHESIS_PROFILE=ci $(PY) -m pytest -q -n 2 --dist loadfile

lint: $(VENV)/.installed-dev
	$(VENV)/bin/ruff check $(LINT_PATHS)
	$(VENV)/bin/ruff format --check $(LINT_PATHS)
	$(VENV)/bin/pyright $(TYPECHECK_PATHS)

# The docs site (mkdocs.yml) into site/; --strict: any warning (a broken link or anchor, a
# docstring griffe cannot parse) fails the build.
docs: $(VENV)/.installed-dev
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --quiet

clean:
	rm -rf $(VENV) results site .pytest_cache
