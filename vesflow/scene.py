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
The reference of every key is ``docs/scene.md``.
"""
from __future__ import annotations

import dataclasses
import difflib
import json
import math
import re
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib

from .errors import SceneError

__all__ = [
    "Scene", "Vesicle", "Lattice", "Flow", "Fluid", "Domain", "Gravity", "Discretization",
    "Time", "Repulsion", "Output", "Effects", "load_scene", "parse_scene", "default_scene",
    "DEFAULT_SCENE_TEXT", "spheroid_axes", "spheroid_reduced_volume", "biconcave_height_scale",
    "euler_zyz", "find_overlaps", "check_overlaps", "SHAPES", "FLOW_TYPES",
]

SHAPES = ("sphere", "ellipsoid", "oblate", "prolate", "biconcave")
FLOW_TYPES = ("shear", "extensional", "poiseuille", "taylor_green")
EVANS_FUNG = (0.207, 2.003, -1.123)
BICONCAVE_V_RANGE = (0.6, 0.7)     # the Evans-Fung profile scaled in height by 0.85 .. 1.3
BICONCAVE_V_DEFAULT = 0.65
P_RANGE = (2, 64)
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
        """Linear factor from the unscaled shape (docs/scene.md) to this vesicle."""
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

    NAMES = {"background_flow": "background flow", "gravity": "gravity", "double_layer": "double layer",
             "repulsion": "repulsion", "periodic": "periodic", "interactions": "near/far field"}

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
                       interactions=len(ves) > 1 or self.domain is not None)

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
        if self.repulsion is not None:
            lines.append(f"repulsion radius {_num(self.repulsion.radius)}")
        eff = self.effects()
        lines.append("effects  on: " + (", ".join(eff.on()) or "none"))
        lines.append("         off: " + (", ".join(eff.off()) or "none"))
        return "\n".join(lines)

    def __str__(self):
        return self.summary()


def _num(x) -> str:
    return f"{x:.6g}"


def _default_dt(horizon: float) -> float:
    return min(0.1, horizon / 10.0)


# ----------------------------------------------------------------------------------------
# Loading
# ----------------------------------------------------------------------------------------
def load_scene(path) -> Scene:
    """Load and validate a scene file; errors are prefixed with the file name."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise _error("scene", f"file {str(path)!r} not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise _error("scene", f"cannot read {str(path)!r}: {exc}") from None
    return parse_scene(text, source=str(path))


def parse_scene(text: str, source: str = "<string>") -> Scene:
    """Parse and validate scene text.  ``source`` names the file in messages and sets the
    default output file ``out/<stem>.h5``."""
    try:
        return _Parser(text, source).scene()
    except SceneError as exc:
        if source and source not in ("<string>",):
            err = SceneError(f"{source}: {exc}")
            err.key = getattr(exc, "key", None)
            raise err from None
        raise


def default_scene() -> Scene:
    """The built-in scene (two vesicles in shear, p = 8, short horizon)."""
    return parse_scene(DEFAULT_SCENE_TEXT, source="<default>")


# ----------------------------------------------------------------------------------------
# Messages
# ----------------------------------------------------------------------------------------
_MISSING = object()


def _fmt(v, limit=60) -> str:
    """A value the way it looks in TOML."""
    if isinstance(v, bool):
        s = "true" if v else "false"
    elif isinstance(v, str):
        s = json.dumps(v, ensure_ascii=False)
    elif isinstance(v, float):
        s = "nan" if v != v else ("inf" if v == math.inf else ("-inf" if v == -math.inf else repr(v)))
    elif isinstance(v, (list, tuple)):
        s = "[" + ", ".join(_fmt(x, limit) for x in v) + "]"
    elif isinstance(v, dict):
        s = "{" + ", ".join(f"{k} = {_fmt(x, limit)}" for k, x in v.items()) + "}"
    else:
        s = str(v)
    return s if len(s) <= limit else s[: limit - 3] + "..."


def _toml_type(v) -> str:
    if isinstance(v, bool):
        return "boolean"
    if isinstance(v, int):
        return "integer"
    if isinstance(v, float):
        return "float"
    if isinstance(v, str):
        return "string"
    if isinstance(v, list):
        return "array"
    if isinstance(v, dict):
        return "table"
    return "date/time"


def _error(path, msg, value=_MISSING) -> SceneError:
    text = f"{path}: {msg}" if value is _MISSING else f"{path} = {_fmt(value)}: {msg}"
    err = SceneError(" ".join(text.split("\n")))
    err.key = path
    return err


def _fail(path, msg, value=_MISSING):
    raise _error(path, msg, value)


def _range_text(gt=None, ge=None, lt=None, le=None) -> str:
    lo = f"({_num(gt)}" if gt is not None else (f"[{_num(ge)}" if ge is not None else None)
    hi = f"{_num(lt)})" if lt is not None else (f"{_num(le)}]" if le is not None else None)
    if lo and hi:
        return f"must be in {lo}, {hi}"
    if lo:
        return f"must be {'>' if gt is not None else '>='} {_num(gt if gt is not None else ge)}"
    if hi:
        return f"must be {'<' if lt is not None else '<='} {_num(lt if lt is not None else le)}"
    return ""


def _check_number(path, v, gt=None, ge=None, lt=None, le=None, hint="") -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        _fail(path, f"expected a number, got {_toml_type(v)}", v)
    x = float(v)
    if not math.isfinite(x):
        _fail(path, "must be a finite number", v)
    bad = ((gt is not None and not x > gt) or (ge is not None and not x >= ge)
           or (lt is not None and not x < lt) or (le is not None and not x <= le))
    if bad:
        _fail(path, _range_text(gt, ge, lt, le) + hint, v)
    return x


def _check_int(path, v, ge=None, le=None) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        _fail(path, f"expected an integer, got {_toml_type(v)}", v)
    if (ge is not None and v < ge) or (le is not None and v > le):
        rng = f"in [{ge}, {le}]" if ge is not None and le is not None else (f">= {ge}" if ge is not None else f"<= {le}")
        _fail(path, f"must be an integer {rng}", v)
    return int(v)


def _check_vec3(path, v, positive=False, what="[x, y, z]") -> tuple[float, float, float]:
    kind = "positive numbers" if positive else "numbers"
    if not isinstance(v, list) or len(v) != 3:
        got = f"{len(v)} items" if isinstance(v, list) else _toml_type(v)
        _fail(path, f"expected 3 {kind} {what}, got {got}", v)
    out = []
    for x in v:
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            _fail(path, f"expected 3 {kind} {what}, got a {_toml_type(x)} among them", v)
        if not math.isfinite(x):
            _fail(path, "all items must be finite numbers", v)
        if positive and not x > 0:
            _fail(path, f"all items must be > 0", v)
        out.append(float(x))
    return tuple(out)


def _check_choice(path, v, choices) -> str:
    if not isinstance(v, str):
        _fail(path, f"expected a string, one of {', '.join(choices)}; got {_toml_type(v)}", v)
    if v not in choices:
        sugg = difflib.get_close_matches(v, choices, n=1, cutoff=0.5)
        _fail(path, f"must be one of {', '.join(choices)}" + (f"; did you mean {_fmt(sugg[0])}?" if sugg else ""), v)
    return v


class _Table:
    """A TOML table under validation: its key path, an unknown-key check, typed getters."""

    def __init__(self, data, path, allowed, hints=None):
        if not isinstance(data, dict):
            _fail(path, f"expected a table, got {_toml_type(data)}", data)
        self.d, self.path = data, path
        for k in data:
            if k in allowed:
                continue
            if hints and k in hints:
                _fail(self.key(k), hints[k])
            sugg = difflib.get_close_matches(k, allowed, n=1, cutoff=0.6)
            _fail(self.key(k), "unknown key; " + (f"did you mean {_fmt(sugg[0])}?" if sugg
                                                   else "valid keys here: " + ", ".join(allowed)))

    def key(self, k):
        return f"{self.path}.{k}" if self.path else k

    def has(self, k):
        return k in self.d

    def _get(self, k, default, required):
        if k in self.d:
            return self.d[k]
        if default is _MISSING:
            _fail(self.key(k), "missing; " + (required or "required"))
        return default

    def number(self, k, default=_MISSING, required=None, **rng):
        v = self._get(k, default, required)
        return v if k not in self.d else _check_number(self.key(k), v, **rng)

    def integer(self, k, default=_MISSING, required=None, **rng):
        v = self._get(k, default, required)
        return v if k not in self.d else _check_int(self.key(k), v, **rng)

    def vec3(self, k, default=_MISSING, required=None, **kw):
        v = self._get(k, default, required)
        return v if k not in self.d else _check_vec3(self.key(k), v, **kw)

    def choice(self, k, choices, default=_MISSING, required=None):
        v = self._get(k, default, required)
        return v if k not in self.d else _check_choice(self.key(k), v, choices)

    def string(self, k, default=_MISSING, required=None):
        v = self._get(k, default, required)
        if k in self.d and not isinstance(v, str):
            _fail(self.key(k), f"expected a string, got {_toml_type(v)}", v)
        return v

    def forbid(self, k, why):
        if k in self.d:
            _fail(self.key(k), why, self.d[k])


# ----------------------------------------------------------------------------------------
# The parser
# ----------------------------------------------------------------------------------------
_TOP = ("title", "flow", "fluid", "domain", "gravity", "discretization", "time", "repulsion",
        "output", "vesicle", "lattice")
_VESICLE_KEYS = ("shape", "reduced_volume", "axes", "radius", "center", "rotation", "bending_modulus",
                 "viscosity_contrast", "excess_density")
_LATTICE_KEYS = ("count", "spacing", "origin", "volume_fraction", "box", "seed", "orientation", "gap",
                 "vesicle") + tuple(f"{k}_spread" for k in SPREAD_KEYS)
_TOP_HINTS = {"vesicles": "unknown key; did you mean \"vesicle\"? (write one [[vesicle]] table per vesicle)",
              "lattices": "unknown key; did you mean \"lattice\"? (write [[lattice]] tables)"}


class _Parser:
    def __init__(self, text, source):
        self.text, self.source = text, source
        self.defaulted = set()

    # -- helpers --------------------------------------------------------------------------
    def _section(self, top, name, allowed, hints=None):
        if name not in top.d:
            return None
        return _Table(top.d[name], name, allowed, hints)

    def _default(self, key, value):
        self.defaulted.add(key)
        return value

    def _toml(self):
        if not isinstance(self.text, str):
            _fail("scene", f"expected TOML text, got {type(self.text).__name__}")
        try:
            return tomllib.loads(self.text)
        except tomllib.TOMLDecodeError as exc:
            msg = str(exc)
            m = re.search(r"\(at line (\d+), column (\d+)\)", msg)
            if m is None:
                m2 = re.search(r"\(at end of document\)", msg)
                where = "end of file" if m2 else "scene"
                _fail(where, "TOML syntax error: " + msg)
            line, col = int(m.group(1)), int(m.group(2))
            lines = self.text.splitlines()
            src = lines[line - 1].strip() if 0 < line <= len(lines) else ""
            reason = msg[: m.start()].strip()
            _fail(f"line {line}, column {col}",
                  f"TOML syntax error: {reason}" + (f" in: {src[:60]}" if src else ""))

    # -- the whole scene ------------------------------------------------------------------
    def scene(self) -> Scene:
        top = _Table(self._toml(), "", _TOP, _TOP_HINTS)
        stem = Path(self.source).stem if self.source not in ("<string>", "<default>", "") else "scene"
        title = top.string("title", default=None)
        if title is None:
            title = stem
        domain = self._domain(top)
        flow = self._flow(top, domain)
        fluid = self._fluid(top)
        gravity = self._gravity(top)
        disc = self._discretization(top)
        time = self._time(top)
        repulsion = self._repulsion(top)
        output = self._output(top, time, stem)
        vesicles = self._vesicles(top)
        lattices = []
        for idx, raw in enumerate(self._array_of_tables(top, "lattice")):
            lat, ves = _LatticeParser(raw, f"lattice[{idx}]", domain, len(vesicles)).build()
            lattices.append(lat)
            vesicles.extend(ves)
            if len(vesicles) > MAX_VESICLES:
                _fail(f"lattice[{idx}]", f"the scene would have {len(vesicles)} vesicles; at most {MAX_VESICLES}")
        if not vesicles:
            _fail("vesicle", "missing; a scene needs at least one [[vesicle]] or [[lattice]] table")
        period = domain.period if domain is not None else None
        check_overlaps(vesicles, period)
        return Scene(title=title, flow=flow, fluid=fluid, domain=domain, gravity=gravity, discretization=disc,
                     time=time, repulsion=repulsion, output=output, vesicles=tuple(vesicles),
                     lattices=tuple(lattices), text=self.text, source=self.source,
                     defaulted=frozenset(self.defaulted))

    def _domain(self, top):
        t = self._section(top, "domain", ("period",))
        if t is None:
            return None
        return Domain(t.number("period", required="the side L of the periodic cube (a number > 0)", gt=0))

    def _flow(self, top, domain):
        t = self._section(top, "flow", ("type", "rate", "radius", "amplitude"))
        if t is None:
            return None
        kind = t.choice("type", FLOW_TYPES, required="one of " + ", ".join(FLOW_TYPES))
        if kind == "taylor_green":
            t.forbid("rate", "not used by flow type \"taylor_green\" (its strength is amplitude)")
            t.forbid("radius", "only used by flow type \"poiseuille\"")
            if domain is None:
                _fail("flow.type", "needs a [domain] table: the Taylor-Green flow is periodic with "
                                   "domain.period", kind)
            return Flow(kind, amplitude=t.number("amplitude", required="the amplitude alpha of the "
                                                 "Taylor-Green flow (a number)"))
        t.forbid("amplitude", "only used by flow type \"taylor_green\"")
        if domain is not None:
            _fail("flow.type", "is not periodic; a [domain] (periodic cube) needs flow type "
                               "\"taylor_green\" or no [flow]", kind)
        rate = t.number("rate", required=f"the rate of the {kind} flow (a number)")
        if kind == "poiseuille":
            return Flow(kind, rate=rate, radius=t.number("radius", required="the pipe radius of the "
                                                          "poiseuille flow (a number > 0)", gt=0))
        t.forbid("radius", "only used by flow type \"poiseuille\"")
        return Flow(kind, rate=rate)

    def _fluid(self, top):
        t = self._section(top, "fluid", ("viscosity",))
        if t is None or not t.has("viscosity"):
            return Fluid(self._default("fluid.viscosity", 1.0))
        return Fluid(t.number("viscosity", gt=0))

    def _gravity(self, top):
        t = self._section(top, "gravity", ("g",))
        if t is None:
            return None
        return Gravity(t.vec3("g", required="the gravity vector [gx, gy, gz]", what="[gx, gy, gz]"))

    def _discretization(self, top):
        t = self._section(top, "discretization", ("p",))
        if t is None or not t.has("p"):
            return Discretization(self._default("discretization.p", 16))
        return Discretization(t.integer("p", ge=P_RANGE[0], le=P_RANGE[1]))

    def _time(self, top):
        t = self._section(top, "time", ("horizon", "dt")) or _Table({}, "time", ())
        horizon = t.number("horizon", default=None, gt=0)
        if horizon is None:
            horizon = self._default("time.horizon", 10.0)
        dt = t.number("dt", default=None, gt=0)
        if dt is None:
            dt = self._default("time.dt", _default_dt(horizon))
        elif dt > horizon:
            _fail("time.dt", f"must be <= time.horizon = {_num(horizon)}", t.d["dt"])
        return Time(horizon=horizon, dt=dt)

    def _repulsion(self, top):
        t = self._section(top, "repulsion", ("radius",))
        if t is None:
            return None
        if not t.has("radius"):
            return Repulsion(self._default("repulsion.radius", 0.02))
        return Repulsion(t.number("radius", gt=0))

    def _output(self, top, time, stem):
        t = self._section(top, "output", ("file", "every")) or _Table({}, "output", ())
        f = t.string("file", default=None)
        if f is None:
            f = self._default("output.file", f"out/{stem}.h5")
        elif not f.strip() or not f.lower().endswith((".h5", ".hdf5")):
            _fail("output.file", "must be a file name ending in .h5 or .hdf5 (HDF5 output)", f)
        every = t.number("every", default=None, gt=0)
        if every is None:
            every = self._default("output.every", time.horizon / 100.0)
        return Output(file=f, every=every)

    def _array_of_tables(self, top, name):
        if name not in top.d:
            return []
        v = top.d[name]
        if isinstance(v, dict):
            _fail(name, f"expected an array of tables: write [[{name}]], not [{name}]")
        if not isinstance(v, list) or not all(isinstance(x, dict) for x in v):
            _fail(name, f"expected an array of tables ([[{name}]]), got {_toml_type(v)}", v)
        return v

    def _vesicles(self, top):
        out = []
        for i, raw in enumerate(self._array_of_tables(top, "vesicle")):
            out.append(_vesicle(raw, f"vesicle[{i}]", label=f"vesicle[{i}]"))
        return out


def _vesicle_fields(raw, path, template=False) -> dict:
    """Validated vesicle keys (center excluded for a lattice template)."""
    hints = {"center": "not allowed here: the lattice sets the centres"} if template else None
    allowed = tuple(k for k in _VESICLE_KEYS if not (template and k == "center"))
    t = _Table(raw, path, allowed, hints)
    shape = t.choice("shape", SHAPES, default=VESICLE_DEFAULTS["shape"])
    out = dict(shape=shape)
    if shape in ("oblate", "prolate"):
        out["reduced_volume"] = t.number("reduced_volume", required=f"shape {_fmt(shape)} needs a reduced volume in "
                                         "(0, 1), for example 0.85", gt=0, lt=1)
    elif shape == "biconcave":
        lo, hi = BICONCAVE_V_RANGE
        out["reduced_volume"] = t.number(
            "reduced_volume", default=BICONCAVE_V_DEFAULT, ge=lo, le=hi,
            hint=" (the biconcave shape is the Evans-Fung profile scaled in height to reach it)")
    else:
        t.forbid("reduced_volume", f"only used by shapes oblate, prolate and biconcave (shape is {_fmt(shape)})")
    if shape == "ellipsoid":
        out["axes"] = t.vec3("axes", required="shape \"ellipsoid\" needs semi-axes [a, b, c]",
                             positive=True, what="[a, b, c]")
    else:
        t.forbid("axes", f"only used by shape \"ellipsoid\" (shape is {_fmt(shape)})")
    out["radius"] = t.number("radius", default=VESICLE_DEFAULTS["radius"], gt=0)
    if not template:
        out["center"] = t.vec3("center", default=VESICLE_DEFAULTS["center"])
    out["rotation"] = t.vec3("rotation", default=VESICLE_DEFAULTS["rotation"], what="[alpha, beta, gamma] (degrees)")
    out["bending_modulus"] = t.number("bending_modulus", default=VESICLE_DEFAULTS["bending_modulus"], gt=0)
    out["viscosity_contrast"] = t.number("viscosity_contrast", default=VESICLE_DEFAULTS["viscosity_contrast"], gt=0)
    out["excess_density"] = t.number("excess_density", default=VESICLE_DEFAULTS["excess_density"])
    out["_given"] = frozenset(raw)
    return out


def _make_vesicle(fields, label) -> Vesicle:
    kw = {k: v for k, v in fields.items() if not k.startswith("_")}
    shape = kw["shape"]
    if shape == "sphere":
        kw["reduced_volume"] = 1.0
    elif shape == "ellipsoid":
        kw["reduced_volume"] = _unit_shape("ellipsoid", None, kw["axes"]).reduced_volume
    return Vesicle(label=label, **kw)


def _vesicle(raw, path, label) -> Vesicle:
    return _make_vesicle(_vesicle_fields(raw, path), label)


# ----------------------------------------------------------------------------------------
# Lattices
# ----------------------------------------------------------------------------------------
class _LatticeParser:
    def __init__(self, raw, path, domain, first):
        self.t = _Table(raw, path, _LATTICE_KEYS)
        self.path, self.domain, self.first = path, domain, first

    def key(self, k):
        return self.t.key(k)

    def build(self):
        t = self.t
        if "vesicle" in t.d:
            if not isinstance(t.d["vesicle"], dict):
                _fail(self.key("vesicle"), "expected an inline table of vesicle keys, for example "
                                           "{ shape = \"oblate\", reduced_volume = 0.85 }", t.d["vesicle"])
            self.tmpl = _vesicle_fields(t.d["vesicle"], self.key("vesicle"), template=True)
        else:
            self.tmpl = _vesicle_fields({}, self.key("vesicle"), template=True)
        self.seed = t.integer("seed", default=0, ge=0)
        self.spreads = self._spreads()
        if t.has("volume_fraction"):
            return self._random()
        if not t.has("count"):
            _fail(self.path, "missing count = [nx, ny, nz] (regular lattice) or volume_fraction (random packing)")
        return self._regular()

    def _spreads(self):
        out = {}
        shape, tmpl = self.tmpl["shape"], self.tmpl
        for k in SPREAD_KEYS:
            name = f"{k}_spread"
            if not self.t.has(name):
                continue
            s = _check_number(self.key(name), self.t.d[name], ge=0, lt=1)
            if k == "reduced_volume":
                if shape not in ("oblate", "prolate", "biconcave"):
                    _fail(self.key(name), f"only used by shapes oblate, prolate and biconcave "
                                          f"(vesicle.shape is {_fmt(shape)})", s)
                v = tmpl["reduced_volume"]
                lo, hi = (0.0, 1.0) if shape != "biconcave" else BICONCAVE_V_RANGE
                if shape != "biconcave" and v * (1 + s) >= 1.0:
                    _fail(self.key(name), f"reduced volumes would reach {_num(v * (1 + s))}; with "
                                          f"reduced_volume = {_num(v)} it must be < {_num(1 / v - 1)}", s)
                if shape == "biconcave" and (v * (1 - s) < lo - 1e-12 or v * (1 + s) > hi + 1e-12):
                    smax = min(1 - lo / v, hi / v - 1)
                    _fail(self.key(name), f"reduced volumes would span [{_num(v * (1 - s))}, {_num(v * (1 + s))}], "
                                          f"outside [{lo}, {hi}] for biconcave; must be <= {_num(smax)}", s)
            out[k] = s
        return out

    def _draw_properties(self, rng, n=None, target_volume=None):
        """Per-vesicle property dicts: n of them, or as many as best fill target_volume."""
        tmpl = self.tmpl
        out, total = [], 0.0
        while True:
            u = rng.uniform(-1.0, 1.0, size=len(SPREAD_KEYS))
            f = dict(tmpl)
            for k, uk in zip(SPREAD_KEYS, u):
                if k in self.spreads and k in f:
                    f[k] = f[k] * (1.0 + self.spreads[k] * uk)
            vol = _make_vesicle(dict(f, center=(0.0, 0.0, 0.0)), "").volume
            if n is None:
                if total + vol > target_volume and (total + vol - target_volume) > (target_volume - total):
                    break
                if len(out) >= MAX_VESICLES:
                    _fail(self.key("volume_fraction"), f"the box would hold more than {MAX_VESICLES} vesicles")
            out.append(f)
            total += vol
            if n is not None and len(out) == n:
                break
        return out, total

    def _rotations(self, rng, n, orientation):
        if orientation == "fixed":
            return [self.tmpl["rotation"]] * n
        u = rng.uniform(size=(n, 3))
        ang = np.column_stack([360.0 * u[:, 0], np.degrees(np.arccos(1.0 - 2.0 * u[:, 1])), 360.0 * u[:, 2]])
        return [tuple(float(x) for x in a) for a in ang]

    def _orientation(self, default):
        o = self.t.choice("orientation", ("fixed", "random"), default=default)
        if o == "random" and "rotation" in self.tmpl["_given"]:
            _fail(self.key("vesicle.rotation"), "cannot be combined with orientation = \"random\"",
                  self.t.d["vesicle"]["rotation"])
        return o

    def _regular(self):
        t, path = self.t, self.path
        for k, why in (("box", "only used by a random packing (with volume_fraction)"),
                       ("gap", "only used by a random packing (with volume_fraction)")):
            t.forbid(k, why)
        raw = t.d["count"]
        if isinstance(raw, int) and not isinstance(raw, bool):
            _fail(self.key("count"), "a regular lattice needs count = [nx, ny, nz] (a single number of vesicles "
                                     "is for a random packing with volume_fraction)", raw)
        if not isinstance(raw, list) or len(raw) != 3:
            _fail(self.key("count"), "expected 3 positive integers [nx, ny, nz]", raw)
        for x in raw:
            if isinstance(x, bool) or not isinstance(x, int) or x < 1:
                _fail(self.key("count"), "expected 3 positive integers [nx, ny, nz]", raw)
        count = tuple(int(x) for x in raw)
        n = count[0] * count[1] * count[2]
        if n > MAX_VESICLES:
            _fail(self.key("count"), f"{n} vesicles; at most {MAX_VESICLES}", raw)
        if t.has("spacing"):
            sp = t.d["spacing"]
            if isinstance(sp, list):
                spacing = _check_vec3(self.key("spacing"), sp, positive=True, what="[sx, sy, sz]")
            else:
                s = _check_number(self.key("spacing"), sp, gt=0)
                spacing = (s, s, s)
            origin = t.vec3("origin", default=(0.0, 0.0, 0.0))
        elif self.domain is not None:
            L = self.domain.period
            spacing = tuple(L / c for c in count)
            origin = t.vec3("origin", default=tuple(0.5 * s for s in spacing))
        else:
            _fail(self.key("spacing"), "missing; a regular lattice needs the distance between centres "
                                       "(a number > 0, or [sx, sy, sz])")
        orientation = self._orientation("fixed")
        rng = np.random.default_rng(self.seed)
        props, _ = self._draw_properties(rng, n=n)
        rots = self._rotations(rng, n, orientation)
        ves = []
        idx = 0
        for k in range(count[2]):
            for j in range(count[1]):
                for i in range(count[0]):
                    c = (origin[0] + i * spacing[0], origin[1] + j * spacing[1], origin[2] + k * spacing[2])
                    f = dict(props[idx], center=c, rotation=rots[idx])
                    ves.append(_make_vesicle(f, f"{path} #{idx} at ({i}, {j}, {k})"))
                    idx += 1
        lat = Lattice("regular", self.first, n, count=count, spacing=spacing, origin=origin, seed=self.seed,
                      orientation=orientation, spreads=tuple(self.spreads.items()))
        return lat, ves

    def _random(self):
        t, path = self.t, self.path
        t.forbid("spacing", "not used by a random packing (volume_fraction given); remove it, "
                            "or remove volume_fraction for a regular lattice")
        phi = _check_number(self.key("volume_fraction"), t.d["volume_fraction"], gt=0, le=0.5)
        gap = t.number("gap", default=0.02, ge=0, le=0.5)
        orientation = self._orientation("random")
        n = None
        if t.has("count"):
            raw = t.d["count"]
            if isinstance(raw, list):
                _fail(self.key("count"), "with volume_fraction, count is the number of vesicles (an integer); "
                                         "[nx, ny, nz] is for a regular lattice without volume_fraction", raw)
            n = _check_int(self.key("count"), raw, ge=1, le=MAX_VESICLES)
        rng = np.random.default_rng(self.seed)
        periodic = False
        if t.has("box"):
            if n is not None:
                _fail(self.key("count"), "give box or count, not both: with volume_fraction either one "
                                         "fixes the other", t.d["count"])
            box = _check_vec3(self.key("box"), t.d["box"], positive=True, what="[Lx, Ly, Lz]")
            props, total = self._draw_properties(rng, target_volume=phi * box[0] * box[1] * box[2])
            if not props:
                _fail(self.key("box"), f"too small for one vesicle at volume_fraction {_num(phi)}", list(box))
            origin = t.vec3("origin", default=tuple(-0.5 * b for b in box))
        elif self.domain is not None:
            if n is not None:
                _fail(self.key("count"), "not allowed with volume_fraction in a periodic [domain]: the number "
                                         "follows from volume_fraction and domain.period (or give a box)", n)
            L = self.domain.period
            box = (L, L, L)
            props, total = self._draw_properties(rng, target_volume=phi * L ** 3)
            if not props:
                _fail(self.key("volume_fraction"), f"too small for one vesicle in the period {_num(L)} cell", phi)
            t.forbid("origin", "not used: a periodic packing fills the domain cell [0, period)^3")
            origin = (0.0, 0.0, 0.0)
            periodic = True
        else:
            if n is None:
                _fail(path, "a random packing needs box = [Lx, Ly, Lz] or count = N (or a periodic [domain])")
            props, total = self._draw_properties(rng, n=n)
            side = (total / phi) ** (1.0 / 3.0)
            box = (side, side, side)
            origin = t.vec3("origin", default=tuple(-0.5 * b for b in box))
        n = len(props)
        rots = self._rotations(rng, n, orientation)
        ves0 = [_make_vesicle(dict(f, center=(0.0, 0.0, 0.0), rotation=r), "") for f, r in zip(props, rots)]
        centers, rotations = _random_packing(ves0, np.asarray(origin), np.asarray(box), periodic, gap, rng,
                                             self.key("volume_fraction"), phi, rotate=orientation == "random")
        if orientation == "fixed":
            rotations = rots
        ves = [_make_vesicle(dict(f, center=tuple(map(float, c)), rotation=tuple(map(float, r))),
                             f"{path} #{i}") for i, (f, c, r) in enumerate(zip(props, centers, rotations))]
        achieved = total / (box[0] * box[1] * box[2])
        lat = Lattice("random", self.first, n, count=n, origin=origin, box=box, periodic=periodic,
                      volume_fraction=phi, achieved_volume_fraction=achieved, seed=self.seed,
                      orientation=orientation, gap=gap, spreads=tuple(self.spreads.items()))
        return lat, ves


# ----------------------------------------------------------------------------------------
# Geometry of the analytic shapes
# ----------------------------------------------------------------------------------------
def euler_zyz(angles_deg) -> np.ndarray:
    """Rotation matrix Rz(alpha) Ry(beta) Rz(gamma) of ZYZ Euler angles in degrees (an active
    rotation about the centre: world = center + R @ body)."""
    a, b, g = np.radians(np.asarray(angles_deg, dtype=float))

    def rz(t):
        c, s = math.cos(t), math.sin(t)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    cb, sb = math.cos(b), math.sin(b)
    ry = np.array([[cb, 0.0, sb], [0.0, 1.0, 0.0], [-sb, 0.0, cb]])
    return rz(a) @ ry @ rz(g)


def _euler_from_matrix(R) -> tuple[float, float, float]:
    """Inverse of euler_zyz (degrees)."""
    b = math.acos(max(-1.0, min(1.0, R[2, 2])))
    if abs(math.sin(b)) > 1e-12:
        a = math.atan2(R[1, 2], R[0, 2])
        g = math.atan2(R[2, 1], -R[2, 0])
    else:  # gimbal lock: only a + g (or a - g) matters
        a = math.atan2(R[1, 0], R[0, 0]) if R[2, 2] > 0 else math.atan2(-R[1, 0], -R[0, 0])
        g = 0.0
    return (math.degrees(a) % 360.0, math.degrees(b), math.degrees(g) % 360.0)


def _spheroid_area(c: float) -> float:
    """Area of the spheroid with semi-axes (1, 1, c)."""
    if abs(c - 1.0) < 1e-9:
        return 4.0 * math.pi * (1.0 + 2.0 * (c - 1.0) / 3.0)  # first order in c - 1
    if c < 1.0:
        e = math.sqrt(1.0 - c * c)
        return 2.0 * math.pi * (1.0 + c * c / e * math.log((1.0 + e) / c))   # atanh(e) = log((1 + e) / c)
    e = math.sqrt(1.0 - 1.0 / (c * c))
    return 2.0 * math.pi * (1.0 + c / e * math.asin(e))


def spheroid_reduced_volume(c: float) -> float:
    """Reduced volume 6 sqrt(pi) V / A^1.5 of the spheroid with semi-axes (1, 1, c)."""
    return 6.0 * math.sqrt(math.pi) * (4.0 / 3.0 * math.pi * c) / _spheroid_area(c) ** 1.5


@lru_cache(maxsize=4096)
def spheroid_axes(kind: str, reduced_volume: float) -> tuple[float, float, float]:
    """Unscaled semi-axes (1, 1, c) of the oblate (c < 1) or prolate (c > 1) spheroid with the
    given reduced volume in (0, 1]; c is along z."""
    from scipy.optimize import brentq

    v = float(reduced_volume)
    if kind not in ("oblate", "prolate"):
        raise ValueError(f"spheroid kind must be 'oblate' or 'prolate', got {kind!r}")
    if not 0.0 < v <= 1.0:
        raise ValueError(f"reduced_volume = {v!r}: must be in (0, 1]")
    if v >= 1.0 - 1e-15:
        return (1.0, 1.0, 1.0)
    f = lambda c: spheroid_reduced_volume(c) - v
    if kind == "oblate":
        c = brentq(f, 1e-12, 1.0 - 1e-12, xtol=1e-15, rtol=1e-15)
    else:
        c = brentq(f, 1.0 + 1e-12, 1e14, xtol=1e-15, rtol=1e-15)
    return (1.0, 1.0, float(c))


def _ellipsoid_area(axes) -> float:
    """Area of the ellipsoid with semi-axes (a, b, c) (Legendre's formula)."""
    from scipy.special import ellipeinc, ellipkinc

    a, b, c = sorted((float(x) for x in axes), reverse=True)
    if a - c < 1e-12 * a:
        return 4.0 * math.pi * a * a
    phi = math.acos(c / a)
    m = (a * a * (b * b - c * c)) / (b * b * (a * a - c * c))
    s = math.sin(phi)
    return 2.0 * math.pi * c * c + 2.0 * math.pi * a * b / s * (
        ellipeinc(phi, m) * s * s + ellipkinc(phi, m) * math.cos(phi) ** 2)


def _biconcave_profile(rho2, s):
    c0, c2, c4 = EVANS_FUNG
    return 0.5 * s * (c0 + c2 * rho2 + c4 * rho2 * rho2)   # times sqrt(1 - rho^2)


@lru_cache(maxsize=None)
def _gl_quarter(n=400):
    x, w = np.polynomial.legendre.leggauss(n)
    return (x + 1.0) * math.pi / 4.0, w * math.pi / 4.0


def _biconcave_area_volume(s: float) -> tuple[float, float]:
    """Area and volume of the Evans-Fung cell of unit radius with height factor s."""
    t, w = _gl_quarter()
    c0, c2, c4 = EVANS_FUNG
    r, rt = np.sin(t), np.cos(t)              # rho = sin t, the profile is smooth in t
    P = c0 + c2 * r ** 2 + c4 * r ** 4
    zt = 0.5 * s * (-np.sin(t) * P + np.cos(t) * (2 * c2 * r * rt + 4 * c4 * r ** 3 * rt))
    area = 4.0 * math.pi * float(np.sum(w * r * np.sqrt(rt ** 2 + zt ** 2)))
    volume = 2.0 * math.pi * s * (c0 / 3.0 + 2.0 * c2 / 15.0 + 8.0 * c4 / 105.0)
    return area, volume


def _reduced_volume(area, volume):
    return 6.0 * math.sqrt(math.pi) * volume / area ** 1.5


@lru_cache(maxsize=4096)
def biconcave_height_scale(reduced_volume: float) -> float:
    """Height factor s of the Evans-Fung profile (s = 1: the published cell, v ~ 0.644)
    giving the requested reduced volume (v is monotone in s on [0.3, 2], v in [0.29, 0.74])."""
    from scipy.optimize import brentq

    v = float(reduced_volume)
    f = lambda s: _reduced_volume(*_biconcave_area_volume(s)) - v
    if not f(0.3) < 0.0 < f(2.0):
        raise ValueError(f"reduced_volume = {v!r}: the biconcave shape reaches [0.29, 0.74]")
    return float(brentq(f, 0.3, 2.0, xtol=1e-14, rtol=1e-15))


@dataclass(frozen=True)
class _Unit:
    """An unscaled shape: quadric (exact) or biconcave, with its enclosing ellipsoid axes."""
    kind: str                 # "quadric" | "biconcave"
    axes: tuple               # semi-axes of the quadric, or of the biconcave's enclosing spheroid
    s: float                  # biconcave height factor (0 for quadrics)
    area: float
    volume: float
    rbound: float

    @property
    def r0(self):
        return math.sqrt(self.area / (4.0 * math.pi))

    @property
    def reduced_volume(self):
        return _reduced_volume(self.area, self.volume)

    def inside(self, x, margin=1e-9):
        """True where the points x (..., 3), in the body frame, are strictly inside."""
        if self.kind == "quadric":
            a = np.asarray(self.axes)
            return np.sum((x / a) ** 2, axis=-1) < 1.0 - margin
        rho2 = x[..., 0] ** 2 + x[..., 1] ** 2
        h = np.sqrt(np.maximum(1.0 - rho2, 0.0)) * _biconcave_profile(rho2, self.s)
        return (rho2 < 1.0 - margin) & (np.abs(x[..., 2]) < h - margin)

    def surface_points(self):
        return _surface_points(self)


@lru_cache(maxsize=4096)
def _unit_shape(shape, reduced_volume, axes) -> _Unit:
    if shape == "sphere":
        return _Unit("quadric", (1.0, 1.0, 1.0), 0.0, 4.0 * math.pi, 4.0 * math.pi / 3.0, 1.0)
    if shape == "ellipsoid":
        ax = tuple(float(a) for a in axes)
        return _Unit("quadric", ax, 0.0, _ellipsoid_area(ax), 4.0 / 3.0 * math.pi * ax[0] * ax[1] * ax[2], max(ax))
    if shape in ("oblate", "prolate"):
        ax = spheroid_axes(shape, reduced_volume)
        return _Unit("quadric", ax, 0.0, _spheroid_area(ax[2]), 4.0 / 3.0 * math.pi * ax[2], max(ax))
    if shape == "biconcave":
        s = biconcave_height_scale(reduced_volume)
        area, volume = _biconcave_area_volume(s)
        c0, c2, c4 = EVANS_FUNG
        pmax = c0 - c2 * c2 / (4.0 * c4) if 0.0 < -c2 / (2.0 * c4) < 1.0 else max(c0, c0 + c2 + c4)
        rho2 = np.linspace(0.0, 1.0, 20001)
        z = np.sqrt(1.0 - rho2) * _biconcave_profile(rho2, s)
        rbound = float(np.sqrt(np.max(rho2 + z * z))) * (1.0 + 1e-9)
        return _Unit("biconcave", (1.0, 1.0, 0.5 * s * pmax * (1.0 + 1e-9)), s, area, volume, rbound)
    raise ValueError(f"unknown shape {shape!r}")


@lru_cache(maxsize=256)
def _surface_points(unit: _Unit, nt=96, nphi=128) -> np.ndarray:
    """Dense surface samples (S, 3) of an unscaled shape (uniform in theta, phi)."""
    t = (np.arange(nt) + 0.5) * math.pi / nt
    f = np.arange(nphi) * 2.0 * math.pi / nphi
    tt, ff = np.meshgrid(t, f, indexing="ij")
    st, ct = np.sin(tt), np.cos(tt)
    if unit.kind == "quadric":
        a, b, c = unit.axes
        pts = np.stack([a * st * np.cos(ff), b * st * np.sin(ff), c * ct], axis=-1)
    else:
        z = ct * _biconcave_profile(st * st, unit.s)
        pts = np.stack([st * np.cos(ff), st * np.sin(ff), z], axis=-1)
    pts = pts.reshape(-1, 3)
    pts.setflags(write=False)
    return pts


# ----------------------------------------------------------------------------------------
# Pair search and the Perram-Wertheim contact function
# ----------------------------------------------------------------------------------------
def _candidate_pairs(c, rb, period):
    """Pairs (i, j, shift) whose bounding spheres (radii rb) overlap, the image c[j] + shift
    being the one that does.  i < j, or i == j with shift != 0 (a periodic self-image)."""
    from scipy.spatial import cKDTree

    n = len(c)
    empty = (np.zeros(0, int), np.zeros(0, int), np.zeros((0, 3)))
    if n == 0:
        return empty
    rmax = float(rb.max())
    if period is None:
        if n < 2:
            return empty
        ij = cKDTree(c).query_pairs(2.0 * rmax, output_type="ndarray")
        i, j = ij[:, 0], ij[:, 1]
        shift = np.zeros((len(i), 3))
    elif 2.0 * rmax < 0.499 * period:
        L = float(period)
        w = np.mod(c, L)
        w[w >= L] = 0.0
        ij = cKDTree(w, boxsize=L).query_pairs(2.0 * rmax, output_type="ndarray")
        i, j = ij[:, 0], ij[:, 1]
        d0 = c[j] - c[i]
        shift = -L * np.round(d0 / L)
    else:
        L = float(period)
        offs = L * np.array([(a, b, d) for a in (-1, 0, 1) for b in (-1, 0, 1) for d in (-1, 0, 1)], float)
        ii, jj, ss = [], [], []
        for a in range(n):
            js = np.arange(a, n)
            d = c[js][:, None, :] + offs[None] - c[a]
            hit = np.linalg.norm(d, axis=-1) < rb[a] + rb[js][:, None]
            same = js[:, None] == a
            # a self-image: keep one of +shift / -shift (and never the zero shift)
            lexpos = (offs[:, 0] > 0) | ((offs[:, 0] == 0) & (offs[:, 1] > 0)) | \
                     ((offs[:, 0] == 0) & (offs[:, 1] == 0) & (offs[:, 2] > 0))
            hit &= ~same | lexpos[None, :]
            jk, ok = np.nonzero(hit)
            ii.append(np.full(len(jk), a))
            jj.append(js[jk])
            ss.append(offs[ok])
        i, j, shift = np.concatenate(ii), np.concatenate(jj), np.concatenate(ss)
    if len(i):
        d = np.linalg.norm(c[j] + shift - c[i], axis=1)
        keep = d <= (rb[i] + rb[j]) * (1.0 + 1e-9)      # touching counts
        i, j, shift = i[keep], j[keep], shift[keep]
        order = np.lexsort((j, i))
        i, j, shift = i[order], j[order], shift[order]
    return i.astype(int), j.astype(int), shift


def _pw(r, MA, MB, iters=44):
    """Perram-Wertheim contact function of ellipsoids {x : x^T MA^-1 x <= 1} and the same with MB
    around r (MA = R diag(a^2) R^T).  Returns mu (both scaled by mu they touch: mu < 1 overlap),
    the optimal lambda and y = C(lambda)^-1 r for the derivatives."""
    L = np.linalg.cholesky(MA)
    Li = np.linalg.inv(L)
    K = Li @ MB @ np.swapaxes(Li, -1, -2)
    k, Q = np.linalg.eigh(K)
    z = np.einsum("pji,pj->pi", Q, np.einsum("pij,pj->pi", Li, r))
    z2 = z * z
    lo = np.zeros(len(r))
    hi = np.ones(len(r))
    for _ in range(iters):     # F(lambda) is concave: bisection on F'
        lam = 0.5 * (lo + hi)
        lm = lam[:, None]
        d = 1.0 - lm + lm * k
        fp = np.sum(z2 * (1.0 - 2.0 * lm - (k - 1.0) * lm * lm) / (d * d), axis=1)
        pos = fp > 0
        lo = np.where(pos, lam, lo)
        hi = np.where(pos, hi, lam)
    lam = 0.5 * (lo + hi)
    d = 1.0 - lam[:, None] + lam[:, None] * k
    F = lam * (1.0 - lam) * np.sum(z2 / d, axis=1)
    y = np.einsum("pji,pj->pi", Li, np.einsum("pij,pj->pi", Q, z / d))
    return np.sqrt(np.maximum(F, 0.0)), lam, y


def _ellipsoid_matrices(rot, axes):
    """M = R diag(axes^2) R^T for (N, 3, 3) rotations and (N, 3) semi-axes."""
    return np.einsum("nij,nj,nkj->nik", rot, axes ** 2, rot)


def _arrays(vesicles):
    c = np.array([v.center for v in vesicles], float).reshape(-1, 3)
    rot = np.array([v.rotation_matrix() for v in vesicles]).reshape(-1, 3, 3)
    scale = np.array([v.scale for v in vesicles])
    units = [v._unit for v in vesicles]
    enc = np.array([u.axes for u in units], float).reshape(-1, 3) * scale[:, None]
    rb = np.array([u.rbound for u in units]) * scale
    return c, rot, scale, units, enc, rb


def _sampled_overlap(ua, ca, Ra, ka, ub, cb, Rb, kb) -> bool:
    """Surface samples of A strictly inside B, or of B inside A."""
    for (u1, c1, R1, k1), (u2, c2, R2, k2) in (((ua, ca, Ra, ka), (ub, cb, Rb, kb)),
                                               ((ub, cb, Rb, kb), (ua, ca, Ra, ka))):
        x = c1 + (k1 * u1.surface_points()) @ R1.T          # world points of 1
        near = np.sum((x - c2) ** 2, axis=1) < (k2 * u2.rbound) ** 2
        if not near.any():
            continue
        xb = ((x[near] - c2) @ R2) / k2                      # body frame of 2
        if u2.inside(xb).any():
            return True
    return False


def find_overlaps(vesicles, period=None, first_only=False):
    """Overlapping (or touching) pairs of vesicles, sorted: a list of (i, j, shift, mu) with
    j's image at center + shift; i == j means a vesicle overlaps its own periodic image.
    mu is the Perram-Wertheim scale factor (< 1) for two quadrics, None for a sampled pair."""
    vesicles = list(vesicles)
    if not vesicles:
        return []
    c, rot, scale, units, enc, rb = _arrays(vesicles)
    i, j, shift = _candidate_pairs(c, rb, period)
    if len(i) == 0:
        return []
    M = _ellipsoid_matrices(rot, enc)
    r = c[j] + shift - c[i]
    mu, _, _ = _pw(r, M[i], M[j])
    exact = np.array([units[a].kind == "quadric" and units[b].kind == "quadric" for a, b in zip(i, j)], bool)
    out = []
    for n in np.nonzero(mu < 1.0 + 1e-9)[0]:
        a, b = int(i[n]), int(j[n])
        if exact[n]:
            out.append((a, b, shift[n], float(mu[n])))
        elif _sampled_overlap(units[a], c[a], rot[a], scale[a], units[b], c[b] + shift[n], rot[b], scale[b]):
            out.append((a, b, shift[n], None))
        if first_only and out:
            break
    return out


def check_overlaps(vesicles, period=None):
    """Raise SceneError naming the first overlapping pair (vesicle indices in the flat list)."""
    vesicles = list(vesicles)
    if period is not None and vesicles:
        total = sum(v.volume for v in vesicles)
        if total > period ** 3:
            _fail("domain.period", f"the vesicles' total volume {_num(total)} exceeds the periodic cell "
                                   f"({_num(period ** 3)}): they must overlap", period)
    found = find_overlaps(vesicles, period, first_only=True)
    if not found:
        return
    a, b, shift, mu = found[0]

    def name(k):
        lab = vesicles[k].label
        return f"vesicle[{k}]" + (f" ({lab})" if lab and lab != f"vesicle[{k}]" else "")

    va, vb = vesicles[a], vesicles[b]
    d = float(np.linalg.norm(np.asarray(vb.center) + shift - np.asarray(va.center)))
    across = "" if not np.any(shift) else f" across the periodic boundary (image shifted by {_fmt([_num(x) for x in shift]).replace(chr(34), '')})"
    if a == b:
        _fail(name(a), f"overlaps its own periodic image: its extent (bounding radius {_num(va.bounding_radius)}) "
                       f"does not fit in domain.period = {_num(period)}")
    if mu is not None:
        if mu >= 1.0 - 1e-6:
            fix = "they touch; move them apart a little"
        elif mu > 1e-12:
            fix = f"they need about {_num(d / mu)} along that line"
        else:
            fix = "they share the same centre"
        why = f"centres {_num(d)} apart, {fix}"
    else:
        why = (f"centres {_num(d)} apart, surface points of one lie inside the other "
               f"(bounding radii {_num(va.bounding_radius)}, {_num(vb.bounding_radius)})")
    err = SceneError(f"{name(a)} and {name(b)} overlap{across}: {why}")
    err.key = f"vesicle[{a}]"
    raise err


# ----------------------------------------------------------------------------------------
# Random packing: relax overlapping enclosing ellipsoids (projection of the contact
# constraints, translations and rotations), Jacobi-style and vectorized
# ----------------------------------------------------------------------------------------
def _rotvec_matrices(w):
    th = np.linalg.norm(w, axis=1)
    k = w / np.where(th > 0, th, 1.0)[:, None]
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, cth = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    return np.eye(3) + s * K + (1.0 - cth) * (K @ K)


def _random_packing(ves0, origin, box, periodic, gap, rng, key, phi, rotate=True, max_iter=None):
    """Centres and Euler angles of a non-overlapping packing of the vesicles ves0 (their shapes,
    sizes and orientations given) in the box [origin, origin + box), periodic or walled."""
    n = len(ves0)
    _, rot, scale, units, enc, rb = _arrays(ves0)
    enc = enc * (1.0 + gap)
    rb = rb * (1.0 + gap)
    ext = np.max(enc, axis=1)
    if periodic:
        if 2.0 * ext.max() >= box[0]:
            _fail(key, f"a vesicle (extent {_num(2 * ext.max())}) does not fit in the periodic cell", phi)
    elif np.any(2.0 * ext.max() >= box):
        _fail(key, f"a vesicle (extent {_num(2 * ext.max())}) does not fit in the box {_fmt([_num(b) for b in box])}", phi)
    # initial centres: best of a few random candidates (largest clearance to those placed)
    c = np.empty((n, 3))
    for a in range(n):
        if periodic:
            cand = origin + rng.uniform(size=(8, 3)) * box
        else:
            cand = origin + ext[a] + rng.uniform(size=(8, 3)) * (box - 2 * ext[a])
        if a == 0:
            c[a] = cand[0]
            continue
        d = cand[:, None, :] - c[None, :a, :]
        if periodic:
            d -= box * np.round(d / box)
        clear = np.min(np.linalg.norm(d, axis=-1) - rb[None, :a], axis=1) - rb[a]
        c[a] = cand[int(np.argmax(clear))]
    R = rot.copy()
    ell = rb.copy()                       # length scale of a rotation
    period = box[0] if periodic else None
    max_sweeps = max_iter or 1500
    target = 1.0 + 1e-3
    sweeps, stall, best, fewest, since_fewest = 0, 0, np.inf, np.inf, 0
    while True:
        if not periodic:
            h = np.sqrt(np.einsum("nij,nj,nij->ni", R, enc ** 2, R))   # half extents along x, y, z
            c = np.clip(c, origin + h, origin + box - h)
        i, j, shift = _candidate_pairs(c, rb, period)
        M = _ellipsoid_matrices(R, enc)
        r = c[j] + shift - c[i]
        mu, lam, y = _pw(r, M[i], M[j]) if len(i) else (np.zeros(0), np.zeros(0), np.zeros((0, 3)))
        nbad = int(np.sum(mu < 1.0))
        if nbad == 0:
            break
        sweeps += 1
        fewest, since_fewest = (nbad, 0) if nbad < fewest else (fewest, since_fewest + 1)
        if sweeps > max_sweeps or since_fewest > 400:
            _fail(key, f"random packing of {n} vesicles did not converge ({nbad} overlapping pairs left after "
                       f"{sweeps} sweeps); lower volume_fraction or gap, or use a regular lattice "
                       "(count + spacing)", phi)
        worst = float(1.0 - mu.min())
        best, stall = (worst, 0) if worst < best * 0.999 else (best, stall + 1)
        sel = mu < target
        i, j, r, mu, lam, y = i[sel], j[sel], r[sel], mu[sel], lam[sel], y[sel]
        lm = lam[:, None]
        mus = np.maximum(mu, 1e-6)[:, None]
        g_r = lm * (1.0 - lm) * y / mus                                  # d mu / d c_j
        g_wi = -lm * (1.0 - lm) ** 2 * np.cross(np.einsum("pij,pj->pi", M[i], y), y) / mus
        g_wj = -lm ** 2 * (1.0 - lm) * np.cross(np.einsum("pij,pj->pi", M[j], y), y) / mus
        wi, wj = (1.0 / ell[i] ** 2, 1.0 / ell[j] ** 2) if rotate else (0.0 * ell[i], 0.0 * ell[j])
        den = 2.0 * np.sum(g_r ** 2, 1) + wi * np.sum(g_wi ** 2, 1) + wj * np.sum(g_wj ** 2, 1)
        step = ((target + 0.01 - mu) / np.maximum(den, 1e-300))[:, None]
        tiny = np.linalg.norm(r, axis=1) < 1e-9 * ell[i]                 # coincident centres
        if tiny.any():
            g_r[tiny] = rng.normal(size=(int(tiny.sum()), 3))
            step[tiny] = 0.1 * ell[i][tiny, None]
        dc = np.zeros((n, 3))
        dw = np.zeros((n, 3))
        cnt = np.zeros(n)
        np.add.at(dc, j, step * g_r)
        np.add.at(dc, i, -step * g_r)
        np.add.at(dw, i, step * wi[:, None] * g_wi)
        np.add.at(dw, j, step * wj[:, None] * g_wj)
        np.add.at(cnt, i, 1.0)
        np.add.at(cnt, j, 1.0)
        relax = 1.0 / np.sqrt(np.maximum(cnt, 1.0))[:, None]             # Jacobi: damp shared moves
        dw = np.clip(dw * relax, -0.3, 0.3)
        c = c + dc * relax
        if stall > 20:                    # jiggle the overlapping ones to leave a jammed state
            c += rng.normal(scale=0.02, size=(n, 3)) * ell[:, None] * (cnt > 0)[:, None]
            stall = 0
        R = _rotvec_matrices(dw) @ R
        if periodic:
            c = origin + np.mod(c - origin, box)
    _random_packing.sweeps = sweeps
    eul = [_euler_from_matrix(Rk) for Rk in R]
    return c, eul
