"""Site registry contract (interfaces.md §2): valid files load, round-trip, and every breach is named."""

import copy
import math
import pickle
import tomllib

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.drivelog import MODEL_PARAMS
from shared.registry import (
    SUPPORTS,
    Bridge,
    RegistryError,
    Route,
    Site,
    VehicleClass,
    dump_site,
    load_site,
    parse_site,
    toml_dumps,
)

PROPERTY = settings(max_examples=40, deadline=None)

# The contract's example, grown by a second route, a spring-supported bridge and a second class.
VALID = """
[[route]]
id = "R1"
length_m = 240.0

[[route]]
id = "rail-2"
length_m = 1000

[[bridge]]
id = "B1"
route = "R1"
start_chainage_m = 110.0     # where the first support is
span_m = 20.0
n_elements = 20
E_pa = 35e9
I_m4 = 1.25                  # design (healthy) value
mass_per_m = 37500.0
depth_m = 1.0
damping_ratio = 0.03
supports = "simply_supported"   # or "rotational_springs"

[[bridge]]
id = "B2"
route = "rail-2"
start_chainage_m = 400
span_m = 30.0
n_elements = 30
E_pa = 3.5e10
I_m4 = 2.0
mass_per_m = 20000
depth_m = 1.8
damping_ratio = 0.0
supports = "rotational_springs"
krot_nm_per_rad = 1e9
inspected = 2024-05-01          # unknown keys are tolerated

[[vehicle_class]]
model = "quarter_car"
mean = {M = 4450, m = 420, K = 5.0e5, k = 1.95e6, c = 2.0e4}
std  = {M = 445,  m = 42,  K = 5.0e4, k = 1.95e5, c = 2.0e3}

[[vehicle_class]]
model = "sprung_mass"
mean = {m = 1000.0, k = 1e6}
std = {m = 0, k = 1e5}

[future_table]
anything = "goes"
"""


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    # Module-scoped: hypothesis re-runs a test body many times within one function-scoped fixture.
    return tmp_path_factory.mktemp("sites")


def write(path, text):
    path.write_text(text, encoding="utf-8")
    return path


def assert_rejected(path, *fragments) -> str:
    with pytest.raises(RegistryError) as info:
        load_site(path)
    msg = str(info.value)
    assert len(msg.splitlines()) == 1, msg
    assert msg.startswith(f"{path}: "), msg
    rest = msg[len(f"{path}: "):]  # so a fragment cannot match the file's own name
    for fragment in fragments:
        assert fragment in rest, (fragment, msg)
    return msg


# --- valid files ------------------------------------------------------------------------------


def test_valid_registry_loads(tmp_path):
    site = load_site(write(tmp_path / "site.toml", VALID))
    assert site.routes == (Route("R1", 240.0), Route("rail-2", 1000.0))
    b1 = site.bridge("B1")
    assert b1 == Bridge("B1", "R1", 110.0, 20.0, 20, 35e9, 1.25, 37500.0, 1.0, 0.03, "simply_supported")
    assert b1.end_chainage_m == 130.0 and b1.EI == pytest.approx(35e9 * 1.25)
    b2 = site.bridge("B2")
    assert b2.supports == "rotational_springs" and b2.krot_nm_per_rad == 1e9
    assert isinstance(b2.start_chainage_m, float) and isinstance(b2.n_elements, int)
    assert site.bridges_on("R1") == (b1,) and site.bridges_on("nowhere") == ()
    assert site.route("rail-2").length_m == 1000.0
    qc = site.vehicle_class("quarter_car")
    assert qc.mean == {"M": 4450.0, "m": 420.0, "K": 5.0e5, "k": 1.95e6, "c": 2.0e4}
    assert qc.std["c"] == 2.0e3 and site.vehicle_class("sprung_mass").std["m"] == 0.0
    for lookup, key in ((site.route, "R9"), (site.bridge, "B9"), (site.vehicle_class, "carriage")):
        with pytest.raises(KeyError):
            lookup(key)


def test_bridges_on_sorts_by_chainage():
    mk = lambda i, s: Bridge(i, "R", s, 10.0, 4, 1e9, 1.0, 1e3, 1.0, 0.02, "simply_supported")  # noqa: E731
    site = Site((Route("R", 500.0),), (mk("late", 300.0), mk("early", 20.0)))
    assert [b.id for b in site.bridges_on("R")] == ["early", "late"]


def test_dump_then_load_is_identity(tmp_path):
    site = load_site(write(tmp_path / "site.toml", VALID))
    dump_site(site, tmp_path / "again.toml")
    assert load_site(tmp_path / "again.toml") == site


ids = st.text(min_size=1, max_size=8).filter(str.strip)
positive = st.floats(min_value=1e-300, max_value=1e300)


@st.composite
def sites(draw) -> Site:
    route_ids = draw(st.lists(ids, min_size=1, max_size=3, unique=True))
    routes = tuple(Route(r, draw(st.floats(10.0, 1e5))) for r in route_ids)
    bridges, bridge_ids = [], draw(st.lists(ids, min_size=2 * len(routes), max_size=2 * len(routes), unique=True))
    for r in routes:
        for k in range(draw(st.integers(0, 2))):  # bridge k lies in the k-th half of the route
            half = r.length_m / 2
            start = k * half + draw(st.floats(0.0, 0.49)) * half
            bridges.append(Bridge(
                id=bridge_ids.pop(), route=r.id, start_chainage_m=start,
                span_m=draw(st.floats(0.01, 0.49)) * half, n_elements=draw(st.integers(1, 200)),
                E_pa=draw(positive), I_m4=draw(positive), mass_per_m=draw(positive), depth_m=draw(positive),
                damping_ratio=draw(st.floats(0.0, 0.999)), supports=draw(st.sampled_from(SUPPORTS)),
                krot_nm_per_rad=draw(st.none() | positive),
            ))
    classes = tuple(
        VehicleClass(
            m,
            {p: draw(positive) for p in MODEL_PARAMS[m]},
            {p: draw(st.just(0.0) | positive) for p in MODEL_PARAMS[m]},
        )
        for m in draw(st.lists(st.sampled_from(sorted(MODEL_PARAMS)), unique=True, max_size=5))
    )
    return Site(routes, tuple(bridges), classes)


@PROPERTY
@given(site=sites())
def test_any_valid_site_round_trips(workdir, site):
    path = workdir / "site.toml"
    dump_site(site, path)
    assert load_site(path) == site


def test_dump_refuses_an_invalid_site_and_writes_nothing(tmp_path):
    bad = Site((Route("R1", 0.0),))
    with pytest.raises(RegistryError, match=r"out\.toml: route\[0\]\.length_m: must be > 0"):
        dump_site(bad, tmp_path / "out.toml")
    assert not (tmp_path / "out.toml").exists()


def test_error_is_a_value_error_and_pickles():
    err = RegistryError("site.toml", "bridge[0].span_m", "must be > 0")
    assert isinstance(err, ValueError) and str(err) == "site.toml: bridge[0].span_m: must be > 0"
    assert str(pickle.loads(pickle.dumps(err))) == str(err)


# --- mutated registries -----------------------------------------------------------------------

BASE = tomllib.loads(VALID)

not_a_number = st.one_of(st.text(max_size=5), st.booleans(), st.lists(st.integers(), max_size=2))
non_finite = st.sampled_from([math.nan, math.inf, -math.inf])
not_positive = st.one_of(st.floats(max_value=0.0), st.integers(max_value=0), non_finite, not_a_number)
negative = st.one_of(st.floats(max_value=-1e-300), st.integers(max_value=-1), non_finite, not_a_number)
not_a_ratio = st.one_of(negative, st.floats(min_value=1.0), st.integers(min_value=1))
not_a_count = st.one_of(st.integers(max_value=0), st.floats(), not_a_number)
not_a_string = st.one_of(st.integers(), st.floats(), st.booleans(), st.lists(st.text(max_size=2), max_size=2),
                         st.sampled_from(["", "   "]))

# (table, index, key) -> values that are wrong on their own, whatever the rest of the file says
FIELD_MUTATIONS = [
    *[(("route", i, "length_m"), not_positive) for i in (0, 1)],
    *[(("route", i, "id"), not_a_string) for i in (0, 1)],
    *[(("bridge", i, k), not_positive)
      for i in (0, 1) for k in ("span_m", "E_pa", "I_m4", "mass_per_m", "depth_m")],
    (("bridge", 1, "krot_nm_per_rad"), not_positive),
    *[(("bridge", i, "start_chainage_m"), negative) for i in (0, 1)],
    *[(("bridge", i, "damping_ratio"), not_a_ratio) for i in (0, 1)],
    *[(("bridge", i, "n_elements"), not_a_count) for i in (0, 1)],
    *[(("bridge", i, k), not_a_string) for i in (0, 1) for k in ("id", "route", "supports")],
    *[(("bridge", i, "supports"), st.text(max_size=20).filter(lambda s: s.strip() and s not in SUPPORTS))
      for i in (0, 1)],
    *[(("bridge", i, "route"), st.text(max_size=6).filter(lambda s: s.strip() and s not in ("R1", "rail-2")))
      for i in (0, 1)],
    *[(("vehicle_class", i, "model"), not_a_string | st.text(max_size=12).filter(
        lambda s: s.strip() and s not in MODEL_PARAMS)) for i in (0, 1)],
    *[(("vehicle_class", i, k), not_positive | st.integers()) for i in (0, 1) for k in ("mean", "std")],
]


@PROPERTY
@given(data=st.data())
def test_bad_field_is_rejected(workdir, data):
    (table, i, key), values = data.draw(st.sampled_from(FIELD_MUTATIONS))
    value = data.draw(values)
    doc = copy.deepcopy(BASE)
    doc[table][i][key] = value
    path = write(workdir / "site.toml", toml_dumps(doc))
    assert_rejected(path, f"{table}[{i}].{key}")


REQUIRED = {
    "route": ("id", "length_m"),
    "bridge": ("id", "route", "start_chainage_m", "span_m", "n_elements", "E_pa", "I_m4", "mass_per_m",
               "depth_m", "damping_ratio", "supports"),
    "vehicle_class": ("model", "mean", "std"),
}


@PROPERTY
@given(table=st.sampled_from(sorted(REQUIRED)), i=st.sampled_from([0, 1]), data=st.data())
def test_missing_field_is_rejected(workdir, table, i, data):
    key = data.draw(st.sampled_from(REQUIRED[table]))
    doc = copy.deepcopy(BASE)
    del doc[table][i][key]
    path = write(workdir / "site.toml", toml_dumps(doc))
    assert_rejected(path, f"{table}[{i}].{key}", "missing")


@PROPERTY
@given(
    i=st.sampled_from([0, 1]),
    part=st.sampled_from(["mean", "std"]),
    kind=st.sampled_from(["value", "missing", "unknown"]),
    data=st.data(),
)
def test_bad_vehicle_param_is_rejected(workdir, i, part, kind, data):
    doc = copy.deepcopy(BASE)
    vc = doc["vehicle_class"][i]
    names = MODEL_PARAMS[vc["model"]]
    if kind == "unknown":
        name = data.draw(st.from_regex(r"[A-Za-z_]\w{0,5}", fullmatch=True).filter(lambda s: s not in names))
        vc[part][name] = 1.0
    else:
        name = data.draw(st.sampled_from(names))
        if kind == "missing":
            del vc[part][name]
        else:
            vc[part][name] = data.draw(not_positive if part == "mean" else negative)
    path = write(workdir / "site.toml", toml_dumps(doc))
    assert_rejected(path, f"vehicle_class[{i}].{part}.{name}")


@PROPERTY
@given(table=st.sampled_from(["route", "bridge", "vehicle_class"]))
def test_duplicate_ids_are_rejected(workdir, table):
    doc = copy.deepcopy(BASE)
    doc[table][1] = copy.deepcopy(doc[table][0])
    if table == "route":
        doc["route"][1]["length_m"] = 1000.0  # keep B2 inside it: the duplicate id is the only fault
        doc["bridge"][1]["route"] = "R1"
        doc["bridge"][1]["start_chainage_m"] = 10.0
    key = "model" if table == "vehicle_class" else "id"
    path = write(workdir / "site.toml", toml_dumps(doc))
    assert_rejected(path, f"{table}[1].{key}", "duplicate")


def test_dangling_route_is_rejected(tmp_path):
    path = write(tmp_path / "site.toml", VALID.replace('route = "rail-2"', 'route = "R3"'))
    assert_rejected(path, "bridge[1].route", "unknown route 'R3'")


def test_bridge_beyond_route_end_is_rejected(tmp_path):
    path = write(tmp_path / "site.toml", VALID.replace("length_m = 240.0", "length_m = 125.0"))
    assert_rejected(path, "bridge[0].start_chainage_m", "beyond the end of route 'R1'")


def test_overlapping_bridges_are_rejected(tmp_path):
    doc = copy.deepcopy(BASE)
    doc["bridge"][1] |= {"route": "R1", "start_chainage_m": 125.0}
    path = write(tmp_path / "site.toml", toml_dumps(doc))
    assert_rejected(path, "bridge[1].start_chainage_m", "overlaps bridge 'B1'")
    doc["bridge"][1]["start_chainage_m"] = 130.0  # end to end is fine
    load_site(write(path, toml_dumps(doc)))


@pytest.mark.parametrize(
    "text, key",
    [
        ("", "route"),
        ("[route]\nid = 'R1'\nlength_m = 1.0\n", "route"),
        ("route = []\n", "route"),
        ("route = [1]\n", "route[0]"),
        ("bridge = 3\n" + VALID, "toml"),  # redefining a key as an array of tables is a TOML error
        ("bridge = 3\n[[route]]\nid = 'R1'\nlength_m = 1.0\n", "bridge"),
        ("[[route]]\nid = 'R1'\nlength_m = 1.0\nbridge = 'x'\n[[bridge\n", "toml"),
    ],
)
def test_malformed_documents_are_rejected(tmp_path, text, key):
    path = write(tmp_path / "site.toml", text)
    assert assert_rejected(path)[len(f"{path}: "):].split(": ")[0] == key


def test_unreadable_files_are_rejected(tmp_path):
    assert_rejected(tmp_path / "absent.toml", "file", "does not exist")
    (tmp_path / "latin1.toml").write_bytes(b"[[route]]\nid = '\xe9'\n")
    assert_rejected(tmp_path / "latin1.toml", "file", "UTF-8")


def test_parse_site_accepts_plain_data():
    site = parse_site({"route": [{"id": "R", "length_m": 5}]}, "inline")
    assert site == Site((Route("R", 5.0),))
    with pytest.raises(RegistryError, match=r"^inline: route\[0\]\.length_m: must be a number"):
        parse_site({"route": [{"id": "R", "length_m": "5"}]}, "inline")
