"""TOML scene text -> Scene, with every key validated (one-line errors)."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib

from ..errors import SceneError
from .geometry import _unit_shape
from .model import (Accuracy, BICONCAVE_V_DEFAULT, BICONCAVE_V_RANGE, DEFAULT_SCENE_TEXT, FLOW_TYPES, MAX_VESICLES, P_RANGE,
                    SHAPES, SPREAD_KEYS, VESICLE_DEFAULTS, Discretization, Domain, Flow, Fluid, Gravity, Lattice,
                    Output, Repulsion, Scene, Time, Vesicle, WALL_P_RANGE, WALL_SHAPES, Wall, _default_dt)
from .packing import _random_packing, check_inside_wall, check_overlaps
from .validate import _Table, _check_int, _check_number, _check_vec3, _error, _fail, _fmt, _num, _toml_type

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


# The parser
# ----------------------------------------------------------------------------------------
_TOP = ("title", "flow", "fluid", "domain", "gravity", "discretization", "time", "repulsion",
        "output", "vesicle", "lattice", "accuracy", "wall")
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
        accuracy = self._accuracy(top)
        wall = self._wall(top, domain, flow)
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
        if wall is not None:
            check_inside_wall(vesicles, wall)
        return Scene(title=title, flow=flow, fluid=fluid, domain=domain, gravity=gravity, discretization=disc,
                     time=time, repulsion=repulsion, output=output, vesicles=tuple(vesicles),
                     lattices=tuple(lattices), accuracy=accuracy, wall=wall, text=self.text, source=self.source,
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

    def _wall(self, top, domain, flow):
        """[wall]: a closed container (sphere of radius R, or ellipsoid of semi-axes [a, b, c])."""
        t = self._section(top, "wall", ("shape", "radius", "axes", "center", "rotation", "p"))
        if t is None:
            return None
        if domain is not None:
            _fail("wall", "a closed container cannot lie in a periodic [domain] (the periodic channel and tube "
                          "are not available yet); remove [domain] or [wall]")
        if flow is not None:
            _fail("flow.type", "a closed container ([wall]) is at rest and holds no background flow; remove "
                               "[flow] (drive the vesicles by gravity or their own forces)", flow.type)
        shape = t.choice("shape", WALL_SHAPES, required="the container's shape: " + " or ".join(WALL_SHAPES))
        if shape == "sphere":
            t.forbid("axes", "only used by wall shape \"ellipsoid\" (a sphere has radius)")
            t.forbid("rotation", "only used by wall shape \"ellipsoid\"")
            R = t.number("radius", required="the container's radius (a number > 0)", gt=0)
            axes = (R, R, R)
        else:
            t.forbid("radius", "only used by wall shape \"sphere\" (an ellipsoid has axes)")
            axes = t.vec3("axes", required="the container's semi-axes [a, b, c]", positive=True, what="[a, b, c]")
        center = t.vec3("center", default=(0.0, 0.0, 0.0))
        rotation = t.vec3("rotation", default=(0.0, 0.0, 0.0))
        p = t.integer("p", default=None, ge=WALL_P_RANGE[0], le=WALL_P_RANGE[1])
        if p is None:
            p = self._default("wall.p", 16)
        return Wall(shape, tuple(float(a) for a in axes), tuple(float(c) for c in center),
                    tuple(float(r) for r in rotation), int(p))

    def _fluid(self, top):
        t = self._section(top, "fluid", ("viscosity",))
        if t is None or not t.has("viscosity"):
            return Fluid(self._default("fluid.viscosity", 1.0))
        return Fluid(t.number("viscosity", gt=0))

    def _optional(self, top, name, keys, build):
        """build(section table) for an optional section, None when the scene has none."""
        t = self._section(top, name, keys)
        return None if t is None else build(t)

    def _gravity(self, top):
        return self._optional(top, "gravity", ("g",), lambda t: Gravity(
            t.vec3("g", required="the gravity vector [gx, gy, gz]", what="[gx, gy, gz]")))

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

    def _accuracy(self, top):
        return self._optional(top, "accuracy", ("error",), lambda t: Accuracy(t.number(
            "error", required="the error the run must reach (a number in (0, 1), e.g. 1e-3: position "
            "error over the vesicle length at the horizon)", gt=0, lt=1)))

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
