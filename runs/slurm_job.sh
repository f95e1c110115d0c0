#!/bin/bash
# SLURM template: one vesflow run under MPI with PETSc options.  Edit the #SBATCH lines.
#SBATCH --job-name=vesflow
#SBATCH --nodes=1
#SBATCH --ntasks-per-node=16
#SBATCH --time=24:00:00
#SBATCH --output=vesflow-%j.log
set -euo pipefail
SCENE=${SCENE:-runs/shear_pair.toml}
OUT=${OUT:-out/$(basename "$SCENE" .toml)-$SLURM_JOB_ID.h5}
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
srun .venv/bin/vesflow run "$SCENE" -o "$OUT" -options_file runs/production.opts -log_view
