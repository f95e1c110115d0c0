#!/usr/bin/env bash
# A small venv at DEST layered on the shared PETSc environment SHARED (tools/setup_env.sh):
# DEST's own site-packages first, then SHARED's (one .pth file); SHARED's MPI libraries
# (mpi4py looks for libmpi under sys.prefix/lib) and MPI launchers are linked into it.
# Packages installed into DEST (`DEST/bin/python -m pip install ...`, pip from SHARED) stay
# in DEST; nothing in SHARED is changed.
#
#   tools/layered_venv.sh DEST SHARED
set -euo pipefail
if [ $# -ne 2 ]; then
  echo "usage: tools/layered_venv.sh DEST SHARED" >&2
  exit 2
fi
DEST=$1
SHARED=$(cd "$2" 2>/dev/null && pwd) || { echo "layered_venv.sh: $2: no such directory" >&2; exit 2; }
if [ ! -x "$SHARED/bin/python" ]; then
  echo "layered_venv.sh: $SHARED/bin/python: not a Python environment" >&2
  exit 2
fi
if [ -e "$DEST" ]; then
  echo "layered_venv.sh: $DEST exists" >&2
  exit 2
fi
purelib='import sysconfig; print(sysconfig.get_path("purelib"))'
"$SHARED/bin/python" -m venv --without-pip "$DEST"
"$SHARED/bin/python" -c "$purelib" > "$("$DEST/bin/python" -c "$purelib")/_vesflow_shared_env.pth"
for f in "$SHARED"/lib/*; do
  case "$(basename "$f")" in python*) ;; *) ln -s "$f" "$DEST/lib/" ;; esac
done
for tool in mpiexec mpiexec.hydra mpirun hydra_pmi_proxy mpicc mpicxx; do
  if [ -e "$SHARED/bin/$tool" ]; then ln -s "$SHARED/bin/$tool" "$DEST/bin/$tool"; fi
done
echo "$SHARED" > "$DEST/.shared-env"
