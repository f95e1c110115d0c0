#!/bin/bash
# SLURM job template for one vesflow run.  Submit from the clone (after `make test` there):
#
#     sbatch runs/slurm_job.sh                                   # runs/shear_pair.toml
#     SCENE=runs/sedimentation.toml sbatch runs/slurm_job.sh
#     OUT=out/shear_pair-1234.h5 sbatch runs/slurm_job.sh        # continue that run (restart)
#     jid=$(sbatch --parsable runs/slurm_job.sh)                 # a chain of jobs for runs longer
#     OUT=out/shear_pair-$jid.h5 sbatch --dependency=afterany:$jid runs/slurm_job.sh   # than --time
#
# If $OUT exists and holds a checkpoint the job continues it (vesflow run --restart, with the
# options stored in the file, the new ones on top); otherwise it starts $SCENE.  Extra options:
# OPTS (options file), EXTRA (more options).
#
# Time limit: --signal=USR1@120 makes SLURM send SIGUSR1 to the ranks 120 s before --time ends;
# vesflow stops at the end of the step it is in, writes a checkpoint of that state, prints
# "vesflow: stopped by SIGUSR1 at t = ..." and exits 138 (docs/howto/cluster_runs.md).  The job
# then submits its continuation (the same $OUT, after this job) unless CHAIN=0; CHAIN counts the
# continuations left (default 20).  Choose the 120 above one step's time (vesflow check SCENE
# estimates it): a run still in its step at the limit is killed and loses the steps since its
# last checkpoint (-ves_checkpoint_every, default: every frame), no more.
#
# MPI: the vesicles are divided among the --ntasks ranks (contiguous blocks in Morton order,
# docs/explanation/parallel.md); each rank may also use --cpus-per-task OpenMP threads in the kernels.
# Under SLURM the ranks are started by srun; elsewhere the same line is
#     mpiexec -n 16 vesflow run SCENE -o OUT -options_file runs/production.opts -log_view
# A job may continue a run written with another number of ranks (the file holds the whole
# state): change --ntasks between jobs at will.  Rank 0 writes the one HDF5 file and prints.
# At most one rank per vesicle (the default scene has two; runs/taylor_green.toml: e.g.
# --ntasks=16 --cpus-per-task=1).  Edit the #SBATCH lines.
#SBATCH --job-name=vesflow
#SBATCH --nodes=1
#SBATCH --ntasks=2
#SBATCH --cpus-per-task=8
#SBATCH --time=24:00:00
#SBATCH --signal=USR1@120
#SBATCH --output=vesflow-%j.log
set -euo pipefail
cd "${SLURM_SUBMIT_DIR:-.}"

# Site modules, if vesflow's environment was built against them (uncomment / adapt):
# module load gcc/12 openmpi/4.1
# The environment of `make test` (PETSc, petsc4py, the Cython kernels):
source .venv/bin/activate

SCENE=${SCENE:-runs/shear_pair.toml}
OUT=${OUT:-out/$(basename "$SCENE" .toml)-${SLURM_JOB_ID:-local}.h5}
OPTS=${OPTS:-runs/production.opts}
EXTRA=${EXTRA:-}
CHAIN=${CHAIN:-20}
export OMP_NUM_THREADS=${SLURM_CPUS_PER_TASK:-${OMP_NUM_THREADS:-1}}
export OMP_PROC_BIND=${OMP_PROC_BIND:-close} OMP_PLACES=${OMP_PLACES:-cores}
mkdir -p "$(dirname "$OUT")"

NTASKS=${SLURM_NTASKS:-1}
if [ -n "${SLURM_JOB_ID:-}" ] && command -v srun >/dev/null; then
    LAUNCH=(srun --ntasks="$NTASKS" --cpus-per-task="$OMP_NUM_THREADS")
else
    LAUNCH=(mpiexec -n "$NTASKS")
fi

# PETSc options go on the command line as usual (-ksp_*, -pc_type, -log_view ...).
rc=0
if [ -f "$OUT" ] && python -c "import sys, vesflow.io as io; io.read_checkpoint(sys.argv[1])" "$OUT" 2>/dev/null; then
    echo "continuing $OUT on $NTASKS ranks"
    # shellcheck disable=SC2086
    "${LAUNCH[@]}" vesflow run --restart "$OUT" $EXTRA -log_view || rc=$?
else
    # shellcheck disable=SC2086
    "${LAUNCH[@]}" vesflow run "$SCENE" -o "$OUT" -options_file "$OPTS" $EXTRA -log_view || rc=$?
fi

# 138 / 143: stopped by SIGUSR1 / SIGTERM at a step boundary with a checkpoint: continue in the
# next job.  0 done, 2 bad input or the file in use, 3 numerical failure or a failed write of
# $OUT: nothing to continue automatically (docs/reference/exit_status.md).
if { [ "$rc" -eq 138 ] || [ "$rc" -eq 143 ]; } && [ -n "${SLURM_JOB_ID:-}" ] && [ "$CHAIN" -gt 0 ]; then
    next=$(sbatch --parsable --dependency=afterany:"$SLURM_JOB_ID" \
           --export=ALL,OUT="$OUT",SCENE="$SCENE",CHAIN=$((CHAIN - 1)) runs/slurm_job.sh)
    echo "stopped at the time limit; $OUT continues in job $next"
fi
exit "$rc"
