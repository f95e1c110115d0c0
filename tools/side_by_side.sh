#!/bin/bash
# One accuracy-cost case of two vesflow trees in the same minutes (docs/explanation/accuracy_cost.md,
# "Side by side"): the OLD tree runs the case once, the NEW tree runs it in a loop until the old
# one is done, so that both see the same machine load (CPU time depends on it on a shared machine).
# Prints one line per run: the tree, solves, GMRES iterations per solve, process CPU seconds and
# the final centroids.  One thread each.
#
#   tools/side_by_side.sh OLD_TREE NEW_TREE P TOL      e.g.
#   git worktree add /tmp/old 171b0a2 && (cd /tmp/old && ln -s $PWD/.venv . && \
#       .venv/bin/python setup.py -q build_ext --inplace)
#   tools/side_by_side.sh /tmp/old . 8 0.04
set -euo pipefail
OLD=$(cd "$1" && pwd); NEW=$(cd "$2" && pwd); P=$3; TOL=$4
HERE=$(cd "$(dirname "$0")/.." && pwd)
CASE='
import sys
try:                                   # the thread policy, where the tree has one (both BLAS copies)
    from vesflow import threads
    threads.configure(1)
except ImportError:
    pass
from vesflow import study, scene as scenemod
p, tol = int(sys.argv[1]), float(sys.argv[2])
sc = scenemod.load_scene(sys.argv[3])
r = study.run_case(sc, study.parse_case(f"{p},{tol},0"))
print(sys.argv[4], "solves", r["n_solves"], "its/solve %.2f" % r["avg_its"], "cpu_s %.2f" % r["cpu"],
      "centroids", [[round(x, 10) for x in c] for c in r["final"]["centroid"]], flush=True)
'
run() {   # run TREE LABEL
  (cd "$1" && PYTHONPATH="$1" OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 \
     "$HERE/.venv/bin/python" -c "$CASE" "$P" "$TOL" "$HERE/runs/accuracy_cost.toml" "$2")
}
run "$OLD" old &
pid=$!
while kill -0 "$pid" 2>/dev/null; do
  run "$NEW" new
done
wait "$pid"
