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
	touch $(STAMP)

# Numba's disk cache of the compiled kernels, filled once after installing and again when
# a kernel's source changes: the old cache files are deleted first, because Numba checks
# only the file a kernel is defined in, and the camera model's terms (model/camera.py) are
# inlined into the bundle kernel (fieldcal/precompile.py)
KERNEL_SOURCES := $(wildcard fieldcal/*/*_kernel.py fieldcal/*/*_kernels.py) \
                  fieldcal/model/camera.py fieldcal/precompile.py
PRECOMPILED    := $(VENV)/.precompiled

$(PRECOMPILED): $(STAMP) $(KERNEL_SOURCES)
	find fieldcal -path '*/__pycache__/*' \( -name '*.nbi' -o -name '*.nbc' \) -delete
	$(PY) -m fieldcal.precompile
	touch $(PRECOMPILED)

demo: $(PRECOMPILED)
	$(VENV)/bin/fieldcal demo

# two workers, one test file each at a time (tests/conftest.py: the longest files first)
test: $(PRECOMPILED)
	$(PY) -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder

check: $(PRECOMPILED)
	$(PY) -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder -m "not slow and not heavy"

lint: $(STAMP)
	$(VENV)/bin/ruff check .

clean:
	-test -x $(VENV)/bin/fieldcal && $(VENV)/bin/fieldcal server stop
	rm -rf $(VENV) .pytest_cache demo-out
