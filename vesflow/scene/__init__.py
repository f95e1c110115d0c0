"""Scene files: load and validate a TOML scene into frozen dataclasses.

    scene = load_scene("runs/shear_pair.toml")     # or parse_scene(text), default_scene()
    print(scene.summary()); scene.effects().on()

Every problem raises :class:`vesflow.errors.SceneError` with one line that names the key
path, the value and the accepted range (``vesicle[3].reduced_volume = 1.2: must be in (0, 1)``).
Lattices (``[[lattice]]``) are expanded into the flat tuple ``Scene.vesicles``: explicit
``[[vesicle]]`` tables first, then each lattice in file order.  The initial vesicles must
not overlap; the check uses the analytic shapes only (no spherical harmonics):

- sphere, ellipsoid, oblate, prolate are quadrics; a pair is decided exactly by the
  Perram-Wertheim contact function (the scale factor at which the two ellipsoids touch);
- the biconcave (Evans-Fung) cell ``|z| <= s/2 sqrt(1 - rho^2)(c0 + c2 rho^2 + c4 rho^4)`` is
  first tested through its enclosing spheroid, then by dense sampling of each surface
  and an inside test against the other (both ways), resolving overlaps deeper than about
  1e-3 of the radius.

Candidates are pruned by bounding spheres with a k-d tree (periodic images included).
The reference of every key is ``docs/reference/scene.md``.

Modules: ``model`` (the frozen objects), ``parser`` (TOML -> Scene), ``validate`` (one-line
errors), ``geometry`` (exact analytic shapes), ``packing`` (overlap checks, random packings).
"""
from __future__ import annotations

from .geometry import biconcave_height_scale, euler_zyz, spheroid_axes, spheroid_reduced_volume
from .model import (DEFAULT_SCENE_TEXT, Accuracy, FLOW_TYPES, SHAPES, Discretization, Domain, Effects, Flow, Fluid,
                    Gravity, Lattice, Output, Repulsion, Scene, Time, Vesicle)
from .packing import check_overlaps, find_overlaps
from .parser import default_scene, load_scene, parse_scene

__all__ = [
    "Scene", "Vesicle", "Lattice", "Flow", "Fluid", "Domain", "Gravity", "Discretization",
    "Time", "Repulsion", "Output", "Accuracy", "Effects", "load_scene", "parse_scene", "default_scene",
    "DEFAULT_SCENE_TEXT", "spheroid_axes", "spheroid_reduced_volume", "biconcave_height_scale",
    "euler_zyz", "find_overlaps", "check_overlaps", "SHAPES", "FLOW_TYPES",
]
