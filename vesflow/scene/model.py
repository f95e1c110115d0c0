"""The frozen scene objects (Scene, Vesicle, Lattice, Flow, ...) and their defaults."""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from .geometry import SHAPES, _unit_shape, euler_zyz  # noqa: F401 (SHAPES re-exported)
from .validate import _fmt, _num

FLOW_TYPES = ("shear", "extensional", "poiseuille", "taylor_green")
BICONCAVE_V_RANGE = (0.6, 0.7)     # the Evans-Fung profile scaled in height by 0.85 .. 1.3
BICONCAVE_V_DEFAULT = 0.65
P_RANGE = (2, 64)
WALL_SHAPES = ("sphere", "ellipsoid")
WALL_P_RANGE = (8, 64)       # [wall] p (a degree below 8 cannot resolve a container; see Wall.p_min)
WALL_GAP = 0.05              # a vesicle stays this fraction of its radius (bounding sphere) away from a wall
MAX_VESICLES = 100_000
VESICLE_DEFAULTS = dict(shape="sphere", radius=1.0, center=(0.0, 0.0, 0.0), rotation=(0.0, 0.0, 0.0),
                        bending_modulus=0.01, viscosity_contrast=1.0, excess_density=0.0)
SPREAD_KEYS = ("radius", "reduced_volume", "bending_modulus", "viscosity_contrast", "excess_density")

DEFAULT_SCENE_TEXT = """\
# vesflow's built-in scene: two oblate vesicles in shear pass each other
# (the two-vesicle case of the paper's Table 3 at p = 8, in units where the shear rate is 1;
# capillary number rate * R^3 / kappa_b = 10 as in the paper).
title = "two vesicles in shear (built-in)"

[flow]
type = "shear"                  # u = rate * (z, 0, 0)
rate = 1.0

[discretization]
p = 8

[time]
horizon = 1.0
dt = 0.05

[repulsion]
radius = 0.06

[output]
file = "out/default.h5"
every = 0.2

[[vesicle]]
shape = "oblate"
reduced_volume = 0.85
center = [-1.6, 0.0, 0.4]       # upper vesicle moves in +x
bending_modulus = 0.1

[[vesicle]]
shape = "oblate"
reduced_volume = 0.85
center = [1.6, 0.0, -0.4]       # lower vesicle moves in -x
bending_modulus = 0.1
"""


# ----------------------------------------------------------------------------------------
# Frozen scene objects
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Flow:
    """Background flow. ``rate`` for shear/extensional/poiseuille, ``radius`` for poiseuille,
    ``amplitude`` (alpha) for taylor_green; unused fields are None."""
    type: str
    rate: float | None = None
    radius: float | None = None
    amplitude: float | None = None

    @property
    def strength(self) -> float:
        return self.amplitude if self.type == "taylor_green" else self.rate


@dataclass(frozen=True)
class Fluid:
    viscosity: float = 1.0


@dataclass(frozen=True)
class Domain:
    """Triply periodic cube [0, period)^3 (centres are taken modulo the period)."""
    period: float


@dataclass(frozen=True)
class Wall:
    """[wall]: a closed container, fixed and no-slip, the vesicles inside it (docs/explanation/walls.md).
    ``axes``: its semi-axes (a sphere of radius R: (R, R, R)), before the rotation (ZYZ Euler
    angles, degrees) about its centre; ``p``: the degree of its spherical-harmonic surface."""
    shape: str
    axes: tuple[float, float, float]
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    p: int = 16

    def rotation_matrix(self) -> np.ndarray:
        return euler_zyz(self.rotation)


@dataclass(frozen=True)
class Gravity:
    g: tuple[float, float, float]


@dataclass(frozen=True)
class Discretization:
    p: int = 16


@dataclass(frozen=True)
class Time:
    horizon: float = 10.0
    dt: float = 0.1


@dataclass(frozen=True)
class Repulsion:
    radius: float = 0.02


@dataclass(frozen=True)
class Accuracy:
    """[accuracy]: the error the run must reach (position error over the vesicle length at the
    horizon); `vesflow run` plans the settings for it (vesflow.planner)."""
    error: float


@dataclass(frozen=True)
class Output:
    file: str = "out/scene.h5"
    every: float = 0.1


@dataclass(frozen=True)
class Vesicle:
    """One vesicle.  ``reduced_volume`` is always the shape's actual reduced volume (1 for a
    sphere, computed for an ellipsoid); ``axes`` is set for ellipsoids only; ``label`` says
    where the vesicle came from (``vesicle[2]`` or ``lattice[0] #17``)."""
    shape: str = "sphere"
    radius: float = 1.0
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    reduced_volume: float = 1.0
    axes: tuple[float, float, float] | None = None
    bending_modulus: float = 0.01
    viscosity_contrast: float = 1.0
    excess_density: float = 0.0
    label: str = field(default="", compare=False)

    @property
    def _unit(self):
        v = self.reduced_volume if self.shape in ("oblate", "prolate", "biconcave") else None
        return _unit_shape(self.shape, v, self.axes)

    @property
    def area(self) -> float:
        return 4.0 * math.pi * self.radius ** 2

    @property
    def volume(self) -> float:
        return self.reduced_volume * 4.0 / 3.0 * math.pi * self.radius ** 3

    @property
    def scale(self) -> float:
        """Linear factor from the unscaled shape (docs/reference/scene.md) to this vesicle."""
        return self.radius / self._unit.r0

    @property
    def bounding_radius(self) -> float:
        return self.scale * self._unit.rbound

    def unit_axes(self) -> tuple[float, float, float]:
        """Semi-axes of the unscaled quadric (x, y, z before rotation); for a biconcave
        cell, its enclosing spheroid."""
        return self._unit.axes

    def rotation_matrix(self) -> np.ndarray:
        return euler_zyz(self.rotation)


@dataclass(frozen=True)
class Lattice:
    """Record of one [[lattice]] table; its vesicles are ``scene.vesicles[first:first + n]``."""
    kind: str                         # "regular" | "random"
    first: int
    n: int
    count: tuple[int, int, int] | int | None = None
    spacing: tuple[float, float, float] | None = None
    origin: tuple[float, float, float] | None = None
    box: tuple[float, float, float] | None = None
    periodic: bool = False
    volume_fraction: float | None = None      # requested
    achieved_volume_fraction: float | None = None
    seed: int = 0
    orientation: str = "fixed"
    gap: float | None = None
    spreads: tuple[tuple[str, float], ...] = ()


@dataclass(frozen=True)
class Effects:
    """Which physical terms a scene switches on (a disabled one costs nothing)."""
    background_flow: bool
    gravity: bool
    double_layer: bool
    repulsion: bool
    periodic: bool
    interactions: bool            # near and far field between vesicles (or periodic images)
    wall: bool = False            # a closed container ([wall])

    NAMES = {"background_flow": "background flow", "gravity": "gravity", "double_layer": "double layer",
             "repulsion": "repulsion", "periodic": "periodic", "interactions": "near/far field", "wall": "wall"}

    def as_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def on(self) -> list[str]:
        return [self.NAMES[k] for k, v in self.as_dict().items() if v]

    def off(self) -> list[str]:
        return [self.NAMES[k] for k, v in self.as_dict().items() if not v]

    def __str__(self):
        return "on: " + (", ".join(self.on()) or "none") + "; off: " + (", ".join(self.off()) or "none")


@dataclass(frozen=True)
class Scene:
    title: str
    flow: Flow | None
    fluid: Fluid
    domain: Domain | None
    gravity: Gravity | None
    discretization: Discretization
    time: Time
    repulsion: Repulsion | None
    output: Output
    vesicles: tuple[Vesicle, ...]
    lattices: tuple[Lattice, ...] = ()
    accuracy: Accuracy | None = None
    wall: Wall | None = None
    text: str = field(default="", repr=False, compare=False)
    source: str = field(default="<string>", compare=False)
    defaulted: frozenset = field(default=frozenset(), repr=False, compare=False)

    @property
    def n_vesicles(self) -> int:
        return len(self.vesicles)

    @property
    def p(self) -> int:
        return self.discretization.p

    @property
    def periodic_length(self) -> float:
        return self.domain.period if self.domain is not None else 0.0

    @property
    def volume_fraction(self) -> float | None:
        """Total vesicle volume over the periodic cell (None in free space)."""
        if self.domain is None:
            return None
        return sum(v.volume for v in self.vesicles) / self.domain.period ** 3

    def effects(self) -> Effects:
        ves = self.vesicles
        flow_on = self.flow is not None and self.flow.strength != 0.0
        g_on = (self.gravity is not None and any(x != 0.0 for x in self.gravity.g)
                and any(v.excess_density != 0.0 for v in ves))
        return Effects(background_flow=flow_on, gravity=g_on,
                       double_layer=any(v.viscosity_contrast != 1.0 for v in ves),
                       repulsion=self.repulsion is not None, periodic=self.domain is not None,
                       interactions=len(ves) > 1 or self.domain is not None, wall=self.wall is not None)

    def replace(self, **changes) -> "Scene":
        """New scene with dotted keys changed, e.g. ``replace(**{"time.horizon": 5.0})``;
        ``"repulsion.radius": None`` (or 0) removes the repulsion.  Defaults derived from the
        horizon (time.dt, output.every) follow it unless they were given."""
        sections = {}
        given = set(changes)
        if "time.horizon" in changes:
            h = float(changes["time.horizon"])
            if "time.dt" in self.defaulted and "time.dt" not in given:
                changes["time.dt"] = _default_dt(h)
            if "output.every" in self.defaulted and "output.every" not in given:
                changes["output.every"] = h / 100.0
        new = dataclasses.replace(self)
        for key, value in changes.items():
            sec, _, name = key.partition(".")
            if sec == "repulsion":
                obj = None if value in (None, 0, 0.0) else Repulsion(float(value))
                new = dataclasses.replace(new, repulsion=obj)
                continue
            if sec not in ("discretization", "time", "output", "fluid") or not name:
                raise KeyError(f"scene key {key!r} cannot be replaced")
            sections.setdefault(sec, {})[name] = value
        for sec, vals in sections.items():
            new = dataclasses.replace(new, **{sec: dataclasses.replace(getattr(new, sec), **vals)})
        return dataclasses.replace(new, defaulted=frozenset(self.defaulted - given))

    def summary(self) -> str:
        ves = self.vesicles
        p = self.p
        per = 4 * (p + 1) ** 2
        shapes = {}
        for v in ves:
            shapes[v.shape] = shapes.get(v.shape, 0) + 1
        radii = [v.radius for v in ves]
        rtxt = f"radius {_num(radii[0])}" if min(radii) == max(radii) else \
            f"radius {_num(min(radii))}..{_num(max(radii))}"
        lines = [f"scene    {self.title!r} ({self.source})",
                 f"vesicles {len(ves)} (" + ", ".join(f"{k} x{n}" for k, n in shapes.items()) + f"), {rtxt}"]
        for lat in self.lattices:
            if lat.kind == "regular":
                lines.append(f"         lattice {lat.count[0]}x{lat.count[1]}x{lat.count[2]}, spacing "
                             + _fmt(list(lat.spacing)) + f", {lat.orientation} orientation")
            else:
                lines.append(f"         random packing of {lat.n}, volume fraction {lat.achieved_volume_fraction:.4g}"
                             f" (asked {lat.volume_fraction:.4g}), seed {lat.seed}"
                             + (", periodic" if lat.periodic else ", box " + _fmt(list(lat.box))))
        lines.append(f"unknowns p = {p}: {per} per vesicle, {per * len(ves)} in all")
        t = self.time
        lines.append(f"time     horizon {_num(t.horizon)}, first dt {_num(t.dt)}; frames every "
                     f"{_num(self.output.every)} -> {self.output.file}")
        f = self.flow
        if f is None:
            lines.append("flow     none (quiescent)")
        elif f.type == "taylor_green":
            lines.append(f"flow     taylor_green, amplitude {_num(f.amplitude)}")
        elif f.type == "poiseuille":
            lines.append(f"flow     poiseuille, rate {_num(f.rate)}, radius {_num(f.radius)}")
        else:
            lines.append(f"flow     {f.type}, rate {_num(f.rate)}")
        lines.append(f"fluid    viscosity {_num(self.fluid.viscosity)}")
        if self.domain is not None:
            lines.append(f"domain   periodic cube, period {_num(self.domain.period)}, volume fraction "
                         f"{self.volume_fraction:.4g}")
        else:
            lines.append("domain   free space")
        if self.gravity is not None:
            lines.append("gravity  g = " + _fmt(list(self.gravity.g)))
        if self.wall is not None:
            w = self.wall
            size = f"radius {_num(w.axes[0])}" if w.shape == "sphere" else "semi-axes " + _fmt(list(w.axes))
            lines.append(f"wall     closed {w.shape} container, {size}, centre {_fmt(list(w.center))}, p = {w.p}")
        if self.repulsion is not None:
            lines.append(f"repulsion radius {_num(self.repulsion.radius)}")
        if self.accuracy is not None:
            lines.append(f"accuracy error {_num(self.accuracy.error)} (vesflow run plans the settings: vesflow plan)")
        eff = self.effects()
        lines.append("effects  on: " + (", ".join(eff.on()) or "none"))
        lines.append("         off: " + (", ".join(eff.off()) or "none"))
        return "\n".join(lines)

    def __str__(self):
        return self.summary()


def _default_dt(horizon: float) -> float:
    return min(0.1, horizon / 10.0)
