# vesflow: the two commands of the README, and a few more.
#   make test      set-up (Debian packages, PETSc env, kernels) then the default tests
#   make run       set-up then the default scene (or SCENE=...) and its movie
#   make test-all  the default tests plus the slow ones and the cheap accuracy-cost study
#   make study     the full accuracy-cost study (docs/study/, about an hour on 2 cores)
SHELL := /bin/bash
PY      := .venv/bin/python
VESFLOW := .venv/bin/vesflow
SCENE   ?=
OUT     ?= out/default.h5
PYTEST  := $(PY) -m pytest
export VTK_DEFAULT_OPENGL_WINDOW ?= vtkEGLRenderWindow
export OMP_NUM_THREADS ?= 2

.PHONY: setup test test-all test-mpi run bench study clean

setup:
	@tools/setup_env.sh

# pytest exits 5 when nothing was collected: that is not a failure of the suite.
define run_pytest
	$(PYTEST) $(1) || { rc=$$?; [ $$rc -eq 5 ] && echo "(no tests collected)" || exit $$rc; }
endef

test: setup
	$(call run_pytest,-m "not slow and not mpi" -q)
	$(MAKE) --no-print-directory test-mpi

test-mpi:
	@if ls tests/mpi/test_*.py >/dev/null 2>&1; then \
	  .venv/bin/mpiexec -n 2 $(PYTEST) -q -m mpi -p no:cacheprovider tests/mpi/test_*.py || { rc=$$?; [ $$rc -eq 5 ] || exit $$rc; }; \
	fi

test-all: setup
	$(call run_pytest,-m "not mpi" -q)
	$(MAKE) --no-print-directory test-mpi

run: setup
	@mkdir -p out
	$(VESFLOW) run $(SCENE) -o $(OUT)
	$(VESFLOW) render $(OUT) -o $(OUT:.h5=.mp4) --frames $(OUT:.h5=_frames)

study: setup
	$(VESFLOW) study accuracy-cost runs/accuracy_cost.toml --out docs/study

bench: setup
	$(PY) benchmarks/run_all.py

clean:
	rm -rf build vesflow/_kernels/*.c vesflow/_kernels/*.so out .pytest_cache
