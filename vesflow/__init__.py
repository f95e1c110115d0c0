"""vesflow: concentrated vesicle suspensions in 3D Stokes flow.

Importing vesflow has no side effects: PETSc is initialized only by entry points
(vesflow.cli) or by the user.
"""
__version__ = "0.1.0"
