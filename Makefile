# The two set-up commands of fieldcal: `make demo` and `make test`.
# Both create .venv on a fresh machine, install the pinned set (requirements.lock) and
# compile the Numba kernels into their disk cache (fieldcal/precompile.py).
# `make check` is the fast tier for daily work (tests/conftest.py: not slow, not heavy).
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

export OPENBLAS_NUM_THREADS ?= 1
export OMP_NUM_THREADS ?= 1
export MKL_NUM_THREADS ?= 1

.PHONY: demo test check lint bench clean

$(STAMP): requirements.lock pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade "pip==26.3"
	$(PY) -m pip install --quiet -r requirements.lock
	$(PY) -m pip install --quiet --no-deps -e .
	$(PY) -m fieldcal.precompile
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/fieldcal demo

# two workers, one test file each at a time (tests/conftest.py: the longest files first)
test: $(STAMP)
	$(PY) -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder

check: $(STAMP)
	$(PY) -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder -m "not slow and not heavy"

lint: $(STAMP)
	$(VENV)/bin/ruff check .

clean:
	-test -x $(VENV)/bin/fieldcal && $(VENV)/bin/fieldcal server stop
	rm -rf $(VENV) .pytest_cache demo-out
