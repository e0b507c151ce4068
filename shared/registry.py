"""The site registry, the input contract naming routes, bridges and vehicle classes (interfaces.md §2)."""

from __future__ import annotations

import datetime
import math
import numbers
import os
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from shared.drivelog import MODEL_PARAMS, one_line
from shared.geo import GeometryError, RouteGeometry, read_geojson_line

SUPPORTS = ("simply_supported", "rotational_springs")
# A registry's length_m and its geometry's geodesic length describe the same chainage: beyond this
# share they disagree about where the route ends.
LENGTH_TOLERANCE = 0.01
# A bridge placed by coordinates farther than this from its route's line is on another road.
MAX_BRIDGE_OFFSET_M = 50.0
DECKS = ("rough", "smooth")


class RegistryError(ValueError):
    """A registry breaks the contract; ``str(err)`` is one line ``<file>: <key path>: <problem>``."""

    def __init__(self, file: str | os.PathLike, key: str, problem: str):
        self.file = str(file)
        self.key = key
        self.problem = problem
        super().__init__(one_line(f"{self.file}: {key}: {problem}"))

    def __reduce__(self):  # keep picklable despite the 3-argument constructor
        return (type(self), (self.file, self.key, self.problem))


@dataclass(frozen=True)
class Route:
    """A route: chainage runs from 0 to ``length_m`` (m).

    ``geometry`` (optional) is its centre line; chainage is then the geodesic length along it from
    its first vertex (`shared.geo.RouteGeometry`).
    """

    id: str
    length_m: float
    geometry: RouteGeometry | None = None


@dataclass(frozen=True)
class Bridge:
    """A beam bridge on a route (SI units: m, Pa, m⁴, kg/m; ``damping_ratio`` dimensionless).

    ``start_chainage_m`` is the route chainage of the first support; ``I_m4`` is the design
    (healthy) second moment of area. ``krot_nm_per_rad`` (N·m/rad), optional, is a nominal
    rotational stiffness of the bearings when ``supports = "rotational_springs"``.
    """

    id: str
    route: str
    start_chainage_m: float
    span_m: float
    n_elements: int
    E_pa: float
    I_m4: float
    mass_per_m: float
    depth_m: float
    damping_ratio: float
    supports: str
    krot_nm_per_rad: float | None = None
    # Optional: "smooth" declares a deck without its own profile (the passes then say more about the
    # stiffness along the span); "rough" (default, the safe assumption) makes the cloud estimate the
    # deck profile.
    deck: str = "rough"

    @property
    def end_chainage_m(self) -> float:
        """Route chainage of the second support, m."""
        return self.start_chainage_m + self.span_m

    @property
    def EI(self) -> float:
        """Design flexural rigidity, N·m²."""
        return self.E_pa * self.I_m4


@dataclass(frozen=True)
class VehicleClass:
    """The prior of a vehicle model's parameters: ``mean`` (> 0) and ``std`` (>= 0) per name."""

    model: str
    mean: dict[str, float]
    std: dict[str, float]


@dataclass(frozen=True)
class Site:
    """Everything the registry describes, with lookups by id."""

    routes: tuple[Route, ...]
    bridges: tuple[Bridge, ...] = ()
    vehicle_classes: tuple[VehicleClass, ...] = ()

    def route(self, route_id: str) -> Route:
        """The route called ``route_id`` (KeyError if none)."""
        for r in self.routes:
            if r.id == route_id:
                return r
        raise KeyError(f"no route {route_id!r} in the site")

    def bridge(self, bridge_id: str) -> Bridge:
        """The bridge called ``bridge_id`` (KeyError if none)."""
        for b in self.bridges:
            if b.id == bridge_id:
                return b
        raise KeyError(f"no bridge {bridge_id!r} in the site")

    def bridges_on(self, route_id: str) -> tuple[Bridge, ...]:
        """The bridges on route ``route_id``, in order of chainage (empty if none)."""
        on_route = (b for b in self.bridges if b.route == route_id)
        return tuple(sorted(on_route, key=lambda b: b.start_chainage_m))

    def vehicle_class(self, model: str) -> VehicleClass:
        """The vehicle class of ``model`` (KeyError if the site has none)."""
        for vc in self.vehicle_classes:
            if vc.model == model:
                return vc
        raise KeyError(f"no vehicle_class for model {model!r} in the site")


# --- reading ----------------------------------------------------------------------------------


def load_site(path: str | os.PathLike) -> Site:
    """Read and validate a site registry.

    Parameters
    ----------
    path : str or PathLike
        A TOML file following interfaces.md §2.

    Raises
    ------
    RegistryError
        If the file is unreadable, not TOML, or breaks the contract; the message names the key.
    """
    name = str(path)
    try:
        text = Path(path).read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise RegistryError(name, "file", "does not exist") from None
    except UnicodeDecodeError:
        raise RegistryError(name, "file", "not valid UTF-8") from None
    except OSError as exc:
        raise RegistryError(name, "file", f"cannot read ({exc.strerror or exc})") from None
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise RegistryError(name, "toml", f"invalid TOML ({exc})") from None
    return parse_site(doc, name)


def parse_site(doc: Mapping[str, Any], name: str = "<site>", base_dir: str | os.PathLike | None = None) -> Site:
    """Validate a registry already parsed into plain data (as `tomllib` returns it).

    ``name`` labels error messages; ``base_dir`` resolves relative ``geometry_file`` paths (default:
    the directory of ``name`` when it is a path). Unknown top-level tables and unknown keys inside
    entries are ignored, so the contract may grow.
    """
    if base_dir is None:
        base_dir = Path(name).parent if not name.startswith("<") else Path.cwd()
    routes = tuple(_route(t, f"route[{i}]", name, Path(base_dir))
                   for i, t in _tables(doc, "route", name, required=True))
    _unique([r.id for r in routes], "route", "id", name)
    by_id = {r.id: r for r in routes}
    bridges = tuple(_bridge(t, f"bridge[{i}]", name, by_id) for i, t in _tables(doc, "bridge", name))
    _unique([b.id for b in bridges], "bridge", "id", name)
    lengths = {r.id: r.length_m for r in routes}
    for i, b in enumerate(bridges):
        kp = f"bridge[{i}]"
        if b.route not in lengths:
            known = ", ".join(lengths)
            raise RegistryError(name, f"{kp}.route", f"unknown route {b.route!r} (routes: {known})")
        if b.end_chainage_m > lengths[b.route]:
            raise RegistryError(
                name,
                f"{kp}.start_chainage_m",
                f"bridge spans {b.start_chainage_m:g}-{b.end_chainage_m:g} m, beyond the end of "
                f"route {b.route!r} (length_m = {lengths[b.route]:g})",
            )
        for other in bridges[:i]:
            if other.route != b.route:
                continue
            if b.start_chainage_m < other.end_chainage_m and other.start_chainage_m < b.end_chainage_m:
                raise RegistryError(
                    name,
                    f"{kp}.start_chainage_m",
                    f"overlaps bridge {other.id!r} ({other.start_chainage_m:g}-{other.end_chainage_m:g} m)",
                )
    classes = tuple(
        _vehicle_class(t, f"vehicle_class[{i}]", name) for i, t in _tables(doc, "vehicle_class", name)
    )
    _unique([c.model for c in classes], "vehicle_class", "model", name)
    return Site(routes, bridges, classes)


def _tables(
    doc: Mapping[str, Any], key: str, file: str, required: bool = False
) -> list[tuple[int, Mapping]]:
    """The entries of array of tables ``key`` with their indices (empty if absent and optional)."""
    if not isinstance(doc, Mapping):
        raise RegistryError(file, "toml", "the document must be a table")
    entries = doc.get(key)
    if entries is None:
        if required:
            raise RegistryError(file, key, f"at least one [[{key}]] is required")
        return []
    if not isinstance(entries, list):
        raise RegistryError(file, key, f"must be an array of tables ([[{key}]]), got {_tname(entries)}")
    if required and not entries:
        raise RegistryError(file, key, f"at least one [[{key}]] is required")
    for i, t in enumerate(entries):
        if not isinstance(t, Mapping):
            raise RegistryError(file, f"{key}[{i}]", f"must be a table, got {_tname(t)}")
    return list(enumerate(entries))


def _unique(values: list[str], table: str, key: str, file: str) -> None:
    seen: dict[str, int] = {}
    for i, v in enumerate(values):
        if v in seen:
            problem = f"duplicate {key} {v!r} (also {table}[{seen[v]}])"
            raise RegistryError(file, f"{table}[{i}].{key}", problem)
        seen[v] = i


def _route(t: Mapping, kp: str, file: str, base_dir: Path) -> Route:
    rid = _string(t, "id", kp, file)
    if "geometry" in t and "geometry_file" in t:
        raise RegistryError(file, f"{kp}.geometry", "give geometry or geometry_file, not both")
    geometry = None
    if "geometry" in t:
        try:
            geometry = RouteGeometry.from_latlon(t["geometry"])
        except GeometryError as e:
            raise RegistryError(file, f"{kp}.geometry", str(e)) from None
    elif "geometry_file" in t:
        rel = _string(t, "geometry_file", kp, file)
        try:
            geometry = read_geojson_line(base_dir / rel)
        except GeometryError as e:
            raise RegistryError(file, f"{kp}.geometry_file", f"{base_dir / rel}: {e}") from None
    if geometry is None or "length_m" in t:
        length = _real(t, "length_m", kp, file, lo=0.0)
    else:
        length = geometry.length_m
    if geometry is not None and abs(length - geometry.length_m) > LENGTH_TOLERANCE * geometry.length_m:
        raise RegistryError(file, f"{kp}.length_m", f"{length:g} m disagrees with the geometry's geodesic "
                            f"length {geometry.length_m:.1f} m by more than {100 * LENGTH_TOLERANCE:g} %")
    return Route(id=rid, length_m=length, geometry=geometry)


def _bridge_start(t: Mapping, kp: str, file: str, routes: Mapping[str, Route]) -> float:
    """The bridge's first support as route chainage: given, or its coordinates on the route's line."""
    if "start_chainage_m" in t or not ("start_lat" in t or "start_lon" in t):
        return _real(t, "start_chainage_m", kp, file, lo=0.0, lo_inclusive=True)
    lat = _real(t, "start_lat", kp, file, lo=-90.0, lo_inclusive=True)
    lon = _real(t, "start_lon", kp, file, lo=-180.0, lo_inclusive=True)
    if abs(lat) > 90.0 or abs(lon) > 180.0:
        raise RegistryError(file, f"{kp}.start_lat", f"({lat:g}, {lon:g}) is not a WGS84 position")
    route = routes.get(t.get("route"))
    if route is None or route.geometry is None:
        raise RegistryError(file, f"{kp}.start_lat", "a position needs a route with geometry; "
                            "give start_chainage_m instead")
    chainage, offset = route.geometry.locate(lat, lon)
    if offset[0] > MAX_BRIDGE_OFFSET_M:
        raise RegistryError(file, f"{kp}.start_lat", f"({lat:g}, {lon:g}) is {offset[0]:.0f} m from route "
                            f"{route.id!r}'s line (more than {MAX_BRIDGE_OFFSET_M:g} m)")
    return float(chainage[0])


def _bridge(t: Mapping, kp: str, file: str, routes: Mapping[str, Route]) -> Bridge:
    fields = dict(
        id=_string(t, "id", kp, file),
        route=_string(t, "route", kp, file),
        start_chainage_m=_bridge_start(t, kp, file, routes),
        span_m=_real(t, "span_m", kp, file, lo=0.0),
        n_elements=_count(t, "n_elements", kp, file),
        E_pa=_real(t, "E_pa", kp, file, lo=0.0),
        I_m4=_real(t, "I_m4", kp, file, lo=0.0),
        mass_per_m=_real(t, "mass_per_m", kp, file, lo=0.0),
        depth_m=_real(t, "depth_m", kp, file, lo=0.0),
        damping_ratio=_real(t, "damping_ratio", kp, file, lo=0.0, lo_inclusive=True, hi=1.0),
        supports=_string(t, "supports", kp, file),
    )
    if fields["supports"] not in SUPPORTS:
        raise RegistryError(
            file,
            f"{kp}.supports",
            f"unknown supports {fields['supports']!r} (expected one of {', '.join(SUPPORTS)})",
        )
    krot = _real(t, "krot_nm_per_rad", kp, file, lo=0.0) if "krot_nm_per_rad" in t else None
    deck = _string(t, "deck", kp, file) if "deck" in t else "rough"
    if deck not in DECKS:
        raise RegistryError(file, f"{kp}.deck", f"unknown deck {deck!r} (expected one of {', '.join(DECKS)})")
    return Bridge(**fields, krot_nm_per_rad=krot, deck=deck)


def _vehicle_class(t: Mapping, kp: str, file: str) -> VehicleClass:
    model = _string(t, "model", kp, file)
    if model not in MODEL_PARAMS:
        known = ", ".join(MODEL_PARAMS)
        raise RegistryError(file, f"{kp}.model", f"unknown model {model!r} (expected one of {known})")
    return VehicleClass(
        model=model,
        mean=_params(t, "mean", model, kp, file, lo_inclusive=False),
        std=_params(t, "std", model, kp, file, lo_inclusive=True),
    )


def _params(t: Mapping, key: str, model: str, kp: str, file: str, lo_inclusive: bool) -> dict[str, float]:
    if key not in t:
        raise RegistryError(file, f"{kp}.{key}", "missing")
    tbl = t[key]
    if not isinstance(tbl, Mapping):
        raise RegistryError(file, f"{kp}.{key}", f"must be a table, got {_tname(tbl)}")
    names = MODEL_PARAMS[model]
    for k in tbl:
        if k not in names:
            problem = f"not a parameter of {model!r} (expected {', '.join(names)})"
            raise RegistryError(file, f"{kp}.{key}.{k}", problem)
    return {k: _real(tbl, k, f"{kp}.{key}", file, lo=0.0, lo_inclusive=lo_inclusive) for k in names}


# --- field checks -----------------------------------------------------------------------------


def _get(t: Mapping, key: str, kp: str, file: str) -> Any:
    if key not in t:
        raise RegistryError(file, f"{kp}.{key}", "missing")
    return t[key]


def _string(t: Mapping, key: str, kp: str, file: str) -> str:
    v = _get(t, key, kp, file)
    if not isinstance(v, str) or not v.strip():
        raise RegistryError(file, f"{kp}.{key}", f"must be a non-empty string, got {_tname(v)} {v!r}")
    return v


def _real(
    t: Mapping,
    key: str,
    kp: str,
    file: str,
    lo: float | None = None,
    lo_inclusive: bool = False,
    hi: float | None = None,
) -> float:
    """A finite number in (lo, hi) — or [lo, hi) with ``lo_inclusive`` — as a float."""
    v = _get(t, key, kp, file)
    where = f"{kp}.{key}"
    if not isinstance(v, numbers.Real) or isinstance(v, bool):
        raise RegistryError(file, where, f"must be a number, got {_tname(v)} {v!r}")
    if not math.isfinite(v):
        raise RegistryError(file, where, f"must be finite, got {v!r}")
    if lo is not None and (v < lo or (v == lo and not lo_inclusive)):
        raise RegistryError(file, where, f"must be {'>=' if lo_inclusive else '>'} {lo:g}, got {v!r}")
    if hi is not None and v >= hi:
        raise RegistryError(file, where, f"must be < {hi:g}, got {v!r}")
    return float(v)


def _count(t: Mapping, key: str, kp: str, file: str) -> int:
    v = _get(t, key, kp, file)
    if not isinstance(v, numbers.Integral) or isinstance(v, bool):
        raise RegistryError(file, f"{kp}.{key}", f"must be an integer, got {_tname(v)} {v!r}")
    if v < 1:
        raise RegistryError(file, f"{kp}.{key}", f"must be >= 1, got {v!r}")
    return int(v)


def _tname(v: Any) -> str:
    if isinstance(v, bool):
        return "boolean"
    if isinstance(v, numbers.Integral):
        return "integer"
    if isinstance(v, numbers.Real):
        return "float"
    return {str: "string", list: "array", dict: "table"}.get(type(v), type(v).__name__)


# --- writing ----------------------------------------------------------------------------------


def site_to_dict(site: Site) -> dict[str, Any]:
    """``site`` as plain data in the registry's layout (what `parse_site` accepts)."""
    doc: dict[str, Any] = {"route": []}
    for r in site.routes:
        entry = {"id": r.id, "length_m": r.length_m}
        if r.geometry is not None:
            entry["geometry"] = r.geometry.latlon()
        doc["route"].append(entry)
    if site.bridges:
        doc["bridge"] = []
        for b in site.bridges:
            entry = {
                "id": b.id,
                "route": b.route,
                "start_chainage_m": b.start_chainage_m,
                "span_m": b.span_m,
                "n_elements": b.n_elements,
                "E_pa": b.E_pa,
                "I_m4": b.I_m4,
                "mass_per_m": b.mass_per_m,
                "depth_m": b.depth_m,
                "damping_ratio": b.damping_ratio,
                "supports": b.supports,
            }
            if b.krot_nm_per_rad is not None:
                entry["krot_nm_per_rad"] = b.krot_nm_per_rad
            entry["deck"] = b.deck
            doc["bridge"].append(entry)
    if site.vehicle_classes:
        doc["vehicle_class"] = [
            {"model": c.model, "mean": dict(c.mean), "std": dict(c.std)} for c in site.vehicle_classes
        ]
    return doc


def dump_site(site: Site, path: str | os.PathLike) -> None:
    """Write ``site`` as a registry TOML file that `load_site` reads back equal.

    The text is validated before anything is written: an invalid site raises `RegistryError`.
    """
    text = toml_dumps(site_to_dict(site))
    parse_site(tomllib.loads(text), str(path))
    Path(path).write_text(text, encoding="utf-8")


def toml_dumps(doc: Mapping[str, Any]) -> str:
    """Emit TOML for the registry's shapes: top-level scalars, and arrays of tables of scalars,
    arrays and inline tables. (Not a general TOML writer: no nested [table] headers.)"""
    head, body = [], []
    for k, v in doc.items():
        if isinstance(v, list) and v and all(isinstance(e, Mapping) for e in v):
            for entry in v:
                body.append(f"\n[[{_toml_key(k)}]]")
                body.extend(f"{_toml_key(kk)} = {_toml_value(vv)}" for kk, vv in entry.items())
        else:
            head.append(f"{_toml_key(k)} = {_toml_value(v)}")
    return "\n".join(head + body).lstrip("\n") + "\n"


_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


def _toml_key(k: str) -> str:
    return k if _BARE_KEY.fullmatch(k) else _toml_string(k)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, numbers.Integral):
        return str(int(v))
    if isinstance(v, numbers.Real):
        v = float(v)
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)  # shortest repr round-trips exactly and is valid TOML ("1e-05", "35000000000.0")
    if isinstance(v, str):
        return _toml_string(v)
    if isinstance(v, (datetime.date, datetime.time)):  # datetime is a date; isoformat() is TOML's form
        return v.isoformat()
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(e) for e in v) + "]"
    if isinstance(v, Mapping):
        return "{" + ", ".join(f"{_toml_key(k)} = {_toml_value(e)}" for k, e in v.items()) + "}"
    raise TypeError(f"cannot write {type(v).__name__} as TOML")


_TOML_ESCAPES = {'"': '\\"', "\\": "\\\\", "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f", "\r": "\\r"}


def _toml_string(s: str) -> str:
    out = []
    for ch in s:
        if ch in _TOML_ESCAPES:
            out.append(_TOML_ESCAPES[ch])
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04X}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'
