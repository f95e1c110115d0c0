"""One-line scene errors: key path, value, accepted range (vesflow.errors.SceneError)."""
from __future__ import annotations

import difflib
import json
import math

from ..errors import SceneError

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


# TOML's name of a parsed value's type; bool before int (a bool is an int)
_TOML_TYPES = ((bool, "boolean"), (int, "integer"), (float, "float"), (str, "string"), (list, "array"),
               (dict, "table"))


def _toml_type(v) -> str:
    return next((name for kind, name in _TOML_TYPES if isinstance(v, kind)), "date/time")


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
            _fail(path, "all items must be > 0", v)
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


def _num(x) -> str:
    return f"{x:.6g}"
