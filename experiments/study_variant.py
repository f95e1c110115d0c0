"""One accuracy-cost case with extra run options, its error against a cached reference case.

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.study_variant REF.json P TOL SCHEME [-opt=value ...]

REF.json: a case file of `vesflow study accuracy-cost` (OUT/cases/*.json); SCHEME as in the study
(euler, sdc, sdc-radau4x2, ...).  Prints the error (vesflow.study.position_error), solves,
accepted and rejected steps and CPU seconds.  Used for the sdc safety-factor and quadrature
comparison of docs/explanation/accuracy_cost.md, e.g.

    ... -m experiments.study_variant /tmp/p8/cases/<hash>_p8_tol0.0001_R0_sdc.json 8 1e-2 sdc-radau3 -ves_adapt_beta=0.75
"""
import json
import sys

from vesflow import study
from vesflow.scene.parser import load_scene


def main(argv):
    if len(argv) < 4:
        sys.exit(__doc__)
    ref = json.load(open(argv[0]))
    p, tol, scheme = int(argv[1]), float(argv[2]), argv[3]
    extra = dict(a.split("=", 1) for a in argv[4:])
    res = study.run_case(load_scene("runs/accuracy_cost.toml"), study.Case(p, tol, 0.0, scheme), extra_options=extra)
    err = study.position_error(res, ref)
    print(f"{scheme} p{p} E/T {tol:g} {extra}: error {err if err is None else format(err, '.3e')} "
          f"solves {res['n_solves']} accepted {res['accepted']} rejected {res['rejected']} cpu {res['cpu']:.1f} s "
          f"({res['status']})", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
