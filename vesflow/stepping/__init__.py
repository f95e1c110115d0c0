"""Time stepping along PETSc TS's seams (docs/explanation/stepping.md).

    State       the run between steps (coefficients, velocity, tension, images, t), copy()
    integrators Euler, SDCIntegrator (+ Doubling, Invariants error estimates): step(state, dt)
    Adaptor     accept / reject, the next dt, landing on output times (TSAdapt)
    PostStep    reparameterization, area/volume correction, collision check, periodic wrap
    monitors    StepLog, Progress, Frames, Checkpoints (TSMonitor)
    Driver      the loop (TSSolve); vesflow.simulation.Run wires it from a scene and options
"""
from .adaptor import Adaptor, QuadratureAdaptor, next_output_time  # noqa: F401
from .driver import Driver  # noqa: F401
from .integrators import Doubling, Euler, Invariants, SDCIntegrator, make_integrator  # noqa: F401
from .monitors import Checkpoints, Frames, Monitor, Progress, StepLog  # noqa: F401
from .poststep import PostStep  # noqa: F401
from .state import State  # noqa: F401
