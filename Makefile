# vesflow: the two commands of the README, and a few more.
#   make test      set-up (Debian packages, PETSc env, kernels) then the default tests
#   make run       set-up then the default scene (or SCENE=...) and its movie
#   make test-all  the default tests plus the slow ones and the cheap accuracy-cost study
#   make study     the accuracy-cost study (docs/study/; cached cases are reused, a fresh run takes hours)
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

# the current study (docs/explanation/accuracy_cost.md): an sdc p = 16 reference, euler and sdc cases
STUDY_CASES := --ref 16,1e-4,0,sdc --case 16,1e-2 --case 16,1e-2,0,sdc --case 10,1e-2,0,sdc \
  --case 16,2.5e-3,0,sdc --case 16,2e-2,0,sdc --case 12,1e-2,0,sdc --case 10,4e-2,0,sdc \
  --case 12,2.5e-3,0,sdc --case 16,2e-2 --case 16,4e-2 --case 12,1e-2 --case 10,2e-2,0.04 --case 8,4e-2 \
  --case 8,4e-2,0,sdc --case 8,1e-2,0,sdc
study: setup
	OMP_NUM_THREADS=1 $(VESFLOW) study accuracy-cost runs/accuracy_cost.toml --out docs/study $(STUDY_CASES)

bench: setup
	$(PY) benchmarks/run_all.py

clean:
	rm -rf build vesflow/_kernels/*.c vesflow/_kernels/*.so out .pytest_cache
