"""Tests of rodsnes.io.scene: reading, deriving and validating the rodsnes options."""
import math

import numpy as np
import pytest
from petsc4py import PETSc

from rodsnes.io import scene
from rodsnes.io.scene import SceneError, check_unknown_options, help_text, read_scene

ARGV = ["rodsnes"]


def _clean(db):
    for k in list(db.getAll()):
        if k.lower().lstrip("-").startswith(scene.RODSNES_PREFIXES):
            db.delValue("-" + k)


@pytest.fixture
def opts():
    """Factory: opts({name: value}) inserts options (value None = bare flag) into
    the global database; everything inserted (and any rodsnes-prefixed leftover)
    is deleted afterwards."""
    db = PETSc.Options()
    _clean(db)
    inserted = []

    def insert(d):
        for k, v in d.items():
            name = k if k.startswith("-") else "-" + k
            db.setValue(name, v)
            inserted.append(name)
        return db

    yield insert
    for name in inserted:
        db.delValue(name)
    _clean(db)


@pytest.fixture
def read(opts):
    def _read(d=None, argv=ARGV):
        opts(d or {})
        return read_scene(argv=argv)
    return _read


@pytest.fixture
def error(opts):
    def _error(d):
        opts(d)
        with pytest.raises(SceneError) as ei:
            read_scene(argv=ARGV)
        return str(ei.value)
    return _error


# ---------------------------------------------------------------------------
def test_defaults(read):
    s = read()
    r = s.rod
    A, I = math.pi * 0.01 ** 2, math.pi * 0.01 ** 4 / 4
    G = 1e6 / 3.0                                   # nu = 0.5
    assert (r.length, r.radius) == (1.0, 0.01)
    assert r.youngs == 1e6 and r.poisson == 0.5
    assert r.shear_modulus == pytest.approx(G, rel=1e-15)
    assert r.shear_coefficient == pytest.approx(0.9, rel=1e-15)   # 6*1.5/(7+3)
    assert r.EA == pytest.approx(1e6 * A, rel=1e-15)
    assert r.GA1 == r.GA2 == pytest.approx(0.9 * G * A, rel=1e-14)
    assert r.EI1 == r.EI2 == pytest.approx(1e6 * I, rel=1e-15)
    assert r.GJ == pytest.approx(G * 2 * I, rel=1e-14)
    assert r.kappa0 is None
    assert (r.shape, r.closed, r.twist_turns, r.imperfection) == ("straight", False, 0.0, 0.0)
    assert r.arc_radius is None and r.helix_radius is None
    assert (r.nelem, r.order, r.quadrature) == (16, 3, "reduced")
    assert (s.bc.start, s.bc.end, s.bc.end_turns) == ("clamped", "free", 0.0)
    L = s.loads
    for v in (L.end_force, L.end_moment, L.gravity):
        assert isinstance(v, np.ndarray) and v.shape == (3,) and v.dtype == float
        assert np.all(v == 0.0)
    assert (L.end_force_follower, L.steps, L.max_cutbacks, L.min_step) == (False, 1, 10, 1e-6)
    c = s.contact
    assert (c.enabled, c.penalty, c.radius, c.exclusion, c.quadrature) == (False, None, None,
                                                                           None, 5)
    assert s.contact_radius == 0.01
    assert (s.output.dir, s.output.quiet, s.output.restart, s.output.case_name) == \
        ("out/default", False, None, "default")
    assert s.stability is False
    assert s.given == ()
    assert all(isinstance(x, float) for x in (r.length, r.EA, r.GJ, L.min_step))


def test_derived_stiffness_from_E_nu_radius(read):
    s = read({"rod_youngs": "2e7", "rod_poisson": "0.3", "rod_radius": "0.02"})
    r = s.rod
    E, nu, rad = 2e7, 0.3, 0.02
    G = E / (2 * 1.3)
    k = 6 * 1.3 / (7 + 6 * 0.3)
    A, I, J = math.pi * rad ** 2, math.pi * rad ** 4 / 4, math.pi * rad ** 4 / 2
    assert r.shear_modulus == pytest.approx(G, rel=1e-14)
    assert r.shear_coefficient == pytest.approx(k, rel=1e-14)
    assert r.EA == pytest.approx(E * A, rel=1e-14)
    assert r.GA1 == pytest.approx(k * G * A, rel=1e-14) and r.GA2 == r.GA1
    assert r.EI1 == pytest.approx(E * I, rel=1e-14) and r.EI2 == r.EI1
    assert r.GJ == pytest.approx(G * J, rel=1e-14)
    np.testing.assert_allclose(np.diag(r.C_bend_twist), [E * I, E * I, G * J], rtol=1e-14)
    np.testing.assert_allclose(np.diag(r.C_shear_stretch), [k * G * A, k * G * A, E * A],
                               rtol=1e-14)


def test_shear_modulus_given_gives_nu_and_k(read):
    r = read({"rod_youngs": "1.2e7", "rod_shear": "5e6"}).rod
    assert r.shear_modulus == 5e6
    assert r.poisson == pytest.approx(0.2, rel=1e-14)          # E/(2G) - 1
    assert r.shear_coefficient == pytest.approx(6 * 1.2 / 8.2, rel=1e-14)
    assert r.GJ == pytest.approx(5e6 * math.pi * 0.01 ** 4 / 2, rel=1e-14)


def test_shear_coefficient_given(read):
    r = read({"rod_shear_coefficient": "0.5"}).rod
    assert r.shear_coefficient == 0.5
    assert r.GA1 == pytest.approx(0.5 * 1e6 / 3 * math.pi * 1e-4, rel=1e-14)


def test_direct_stiffness_overrides_only_that_stiffness(read):
    r = read({"rod_EA": "7", "rod_GJ": "3"}).rod
    assert (r.EA, r.GJ) == (7.0, 3.0)
    assert r.EI1 == pytest.approx(1e6 * math.pi * 1e-8 / 4, rel=1e-15)
    assert r.GA1 == pytest.approx(0.9 * 1e6 / 3 * math.pi * 1e-4, rel=1e-14)


def test_direct_EI_sets_both_axes_and_EI1_only_one(opts, read):
    r = read({"rod_EI": "2.5"}).rod
    assert (r.EI1, r.EI2) == (2.5, 2.5)
    PETSc.Options().delValue("-rod_EI")
    r = read({"rod_EI1": "4"}).rod
    assert r.EI1 == 4.0
    assert r.EI2 == pytest.approx(1e6 * math.pi * 1e-8 / 4, rel=1e-15)


def test_all_direct_stiffnesses_make_material_unused(read):
    r = read({"rod_youngs": "5", "rod_EA": "1", "rod_GA": "2", "rod_EI1": "3",
              "rod_EI2": "4", "rod_GJ": "5"}).rod
    assert (r.EA, r.GA1, r.GA2, r.EI1, r.EI2, r.GJ) == (1.0, 2.0, 2.0, 3.0, 4.0, 5.0)
    assert (r.youngs, r.shear_modulus, r.poisson, r.shear_coefficient) == (None,) * 4


def test_case_insensitive_option_names(read):
    assert read({"rod_ea": "9"}).rod.EA == 9.0


# --- vectors -----------------------------------------------------------------
def test_vector_parsing(read):
    s = read({"load_end_force": "1, 2,-3.5", "load_gravity": "0,0,-9.81",
              "rod_kappa0": "0,0.5,1e-1", "bc_end": "sliding"})
    np.testing.assert_array_equal(s.loads.end_force, [1.0, 2.0, -3.5])
    np.testing.assert_array_equal(s.loads.gravity, [0.0, 0.0, -9.81])
    np.testing.assert_array_equal(s.rod.kappa0, [0.0, 0.5, 0.1])
    assert s.rod.kappa0.shape == (3,) and s.rod.kappa0.dtype == float


@pytest.mark.parametrize("value, expect", [
    ("1,2", "-load_end_moment = 1,2: expected three comma-separated numbers mx,my,mz"),
    ("1,2,3,4", "got 4 values"),
    ("1,x,3", "not all are finite numbers"),
    ("1,nan,3", "not all are finite numbers"),
    ("1;2;3", "got 1 value"),
])
def test_vector_malformed(error, value, expect):
    msg = error({"load_end_moment": value, "bc_end": "pinned"})
    assert expect in msg
    assert "-load_end_moment" in msg


# --- non-numeric values --------------------------------------------------------
@pytest.mark.parametrize("d, expect", [
    ({"rod_length": "abc"}, "-rod_length = abc: not a real number (expected e.g. -rod_length 1)"),
    ({"rod_length": "inf"}, "-rod_length = inf: not a real number"),
    ({"rod_nelem": "3.5"}, "-rod_nelem = 3.5: not an integer (expected e.g. -rod_nelem 16)"),
    ({"rod_nelem": "ten"}, "-rod_nelem = ten: not an integer"),
    ({"rod_radius": None}, "-rod_radius: given without a value"),
    ({"contact": "maybe"}, "-contact = maybe: not a true/false value"),
    ({"rod_shape": "helx"}, "-rod_shape = helx: not an accepted value; accepted: straight, arc, "
                            "circle, helix (did you mean helix?)"),
])
def test_malformed_values(error, d, expect):
    assert expect in error(d)


def test_parse_errors_all_reported_at_once(error):
    msg = error({"rod_length": "x", "rod_order": "y"})
    assert "-rod_length = x" in msg and "-rod_order = y" in msg


def test_integer_written_as_float(read):
    assert read({"rod_nelem": "1e2"}).rod.nelem == 100


# --- flags --------------------------------------------------------------------
@pytest.mark.parametrize("value, expect", [
    (None, True), ("", True), ("1", True), ("true", True), ("yes", True), ("ON", True),
    ("0", False), ("false", False), ("no", False), ("off", False)])
def test_flag_semantics(read, value, expect):
    s = read({"contact": value, "quiet": value, "stability": value,
              "load_end_force_follower": value})
    assert s.contact.enabled is expect
    assert s.output.quiet is expect
    assert s.stability is expect
    assert s.loads.end_force_follower is expect


def test_rod_closed_flag_with_circle(read):
    s = read({"rod_shape": "circle", "rod_closed": None})
    assert s.rod.closed is True
    s2 = read({"rod_closed": "true"})
    assert s2.rod.closed is True


# --- validation ------------------------------------------------------------------
VALIDATION = [
    ({"rod_length": "-1"}, ["-rod_length = -1: must be > 0"]),
    ({"rod_radius": "-1"},
     ["-rod_radius = -1: must be > 0 (the rod's cross-section radius, in length units)"]),
    ({"rod_radius": "0"}, ["-rod_radius = 0: must be > 0"]),
    ({"rod_radius": "0.6"}, ["-rod_radius = 0.6 with -rod_length = 1", "half the length"]),
    ({"rod_youngs": "-2e6"}, ["-rod_youngs = -2e6: must be > 0"]),
    ({"rod_shear": "0"}, ["-rod_shear = 0: must be > 0"]),
    ({"rod_EA": "0"}, ["-rod_EA = 0: must be > 0"]),
    ({"rod_GA": "-1"}, ["-rod_GA = -1: must be > 0"]),
    ({"rod_EI": "0"}, ["-rod_EI = 0: must be > 0"]),
    ({"rod_EI1": "-3"}, ["-rod_EI1 = -3: must be > 0"]),
    ({"rod_EI2": "0"}, ["-rod_EI2 = 0: must be > 0"]),
    ({"rod_GJ": "0"}, ["-rod_GJ = 0: must be > 0"]),
    ({"rod_shear_coefficient": "0"}, ["-rod_shear_coefficient = 0: must be > 0"]),
    ({"rod_poisson": "0.6"}, ["-rod_poisson = 0.6: must be in (-1, 0.5]"]),
    ({"rod_poisson": "-1"}, ["-rod_poisson = -1: must be in (-1, 0.5]"]),
    ({"rod_shear": "4e5", "rod_poisson": "0.3"},
     ["-rod_shear = 4e5 and -rod_poisson = 0.3: give the shear modulus or Poisson's ratio, "
      "not both"]),
    ({"rod_EI": "1", "rod_EI2": "2"}, ["-rod_EI = 1 together with -rod_EI2 = 2"]),
    ({"rod_shear": "1e5"}, ["-rod_shear = 1e5 with -rod_youngs = 1e+06 implies Poisson's ratio "
                            "nu = E/(2G) - 1 = 4"]),
    ({"rod_nelem": "0"}, ["-rod_nelem = 0: must be >= 1"]),
    ({"rod_order": "5"}, ["-rod_order = 5: must be in 1..4"]),
    ({"rod_order": "0"}, ["-rod_order = 0: must be in 1..4"]),
    ({"rod_quadrature": "exact"}, ["-rod_quadrature = exact", "accepted: full, reduced"]),
    ({"rod_shape": "spiral"}, ["-rod_shape = spiral", "accepted: straight, arc, circle, helix"]),
    ({"bc_start": "sliding"}, ["-bc_start = sliding", "accepted: clamped, pinned, free"]),
    ({"bc_end": "glued"}, ["-bc_end = glued", "accepted: clamped, pinned, free, sliding"]),
    ({"rod_closed": None}, ["-rod_closed with -rod_shape = straight: a closed rod needs "
                            "-rod_shape circle"]),
    ({"rod_closed": "1", "rod_shape": "helix", "rod_helix_radius": "0.1",
      "rod_helix_pitch": "0.05"}, ["a closed rod needs -rod_shape circle"]),
    ({"rod_shape": "circle", "rod_closed": "false"}, ["-rod_closed = false with -rod_shape circle",
                                                      "-rod_shape arc -rod_arc_angle 360"]),
    ({"rod_shape": "circle", "bc_start": "pinned"}, ["-bc_start = pinned on a closed ring"]),
    ({"rod_shape": "circle", "bc_end": "clamped"}, ["-bc_end = clamped on a closed ring"]),
    ({"rod_shape": "circle", "bc_end_turns": "1"}, ["-bc_end_turns = 1 on a closed ring"]),
    ({"bc_end": "pinned", "bc_end_turns": "2"}, ["-bc_end_turns = 2 with -bc_end pinned: "
                                                 "nothing to turn"]),
    ({"bc_end_turns": "0.5"}, ["-bc_end_turns = 0.5 with -bc_end free: nothing to turn"]),
    ({"rod_shape": "circle", "rod_twist_turns": "0.5"},
     ["-rod_twist_turns = 0.5 on a closed ring", "whole number of turns"]),
    ({"load_steps": "0"}, ["-load_steps = 0: must be >= 1"]),
    ({"load_max_cutbacks": "-1"}, ["-load_max_cutbacks = -1: must be >= 0"]),
    ({"load_min_step": "0"}, ["-load_min_step = 0: must be in [1e-12, 1]"]),
    ({"load_stop": "1.5"}, ["-load_stop = 1.5: must be in (0, 1]"]),
    ({"contact_penalty": "0"}, ["-contact_penalty = 0: must be > 0"]),
    ({"contact_radius": "-0.01"}, ["-contact_radius = -0.01: must be > 0"]),
    ({"contact_exclusion": "-0.1"}, ["-contact_exclusion = -0.1: must be >= 0"]),
    ({"contact_quadrature": "0"}, ["-contact_quadrature = 0: must be >= 1"]),
    ({"contact_penetration": "0"}, ["-contact_penetration = 0: must be in (0, 0.5]", "a fraction of the contact diameter"]),
    ({"contact_penetration": "1"}, ["-contact_penetration = 1: must be in (0, 0.5]"]),
    ({"rod_shape": "arc", "rod_arc_angle": "400"},
     ["-rod_arc_angle = 400: must be in (0, 360]", "use -rod_shape circle"]),
    ({"rod_shape": "arc", "rod_arc_radius": "0.1"},
     ["-rod_arc_radius = 0.1 with -rod_length = 1 makes an arc of 572.958 degrees > 360",
      "use -rod_shape circle"]),
    ({"rod_shape": "arc"}, ["-rod_shape arc needs -rod_arc_radius R or -rod_arc_angle DEG"]),
    ({"rod_shape": "arc", "rod_arc_radius": "1", "rod_arc_angle": "90"},
     ["-rod_arc_radius = 1 and -rod_arc_angle = 90 are inconsistent with -rod_length = 1"]),
    ({"rod_shape": "circle", "rod_arc_radius": "0.16"},
     ["-rod_arc_radius = 0.16 with -rod_length = 1 and -rod_shape circle", "0.1591549431"]),
    ({"rod_shape": "circle", "rod_arc_angle": "180"}, ["-rod_arc_angle = 180 with -rod_shape "
                                                       "circle"]),
    ({"rod_shape": "helix", "rod_helix_radius": "0", "rod_helix_pitch": "0.1"},
     ["-rod_helix_radius = 0: must be > 0"]),
    ({"rod_shape": "helix", "rod_helix_radius": "0.1", "rod_helix_pitch": "0"},
     ["-rod_helix_pitch = 0: the pitch must be nonzero"]),
    ({"rod_shape": "helix", "rod_helix_radius": "0.1"}, ["-rod_shape helix needs "
                                                         "-rod_helix_pitch"]),
    ({"rod_shape": "helix"}, ["needs -rod_helix_radius and -rod_helix_pitch"]),
    ({"rod_shape": "helix", "rod_helix_radius": "0.1", "rod_helix_pitch": "0.01",
      "contact": None}, ["-rod_helix_pitch = 0.01 with contact radius 0.01",
                         "neighbouring turns interpenetrate"]),
    ({"rod_shape": "arc", "rod_arc_angle": "360", "rod_radius": "0.2"},
     ["not larger than the rod radius"]),
    ({"rod_shape": "arc", "rod_arc_radius": "0.2", "contact": None, "contact_radius": "0.25"},
     ["-rod_arc_radius = 0.2: the reference centreline bends to curvature 5, above 1/contact "
      "radius = 4", "-contact_curvature false"]),
    ({"rod_kappa0": "30,0,0", "contact": None, "rod_radius": "0.02", "contact_radius": "0.05"},
     ["-rod_kappa0 = 30,0,0: the reference centreline bends to curvature 30, above 1/contact "
      "radius = 20"]),
    ({"rod_kappa0": "60,80,0", "rod_radius": "0.01"},          # flexure 100 = 1/radius
     ["-rod_kappa0 = 60,80,0 with -rod_radius = 0.01: the intrinsic flexure |(k1, k2)| = 100 "
      "is not below 1/radius = 100", "fold through itself"]),
    ({"load_end_force": "0,0,1", "bc_end": "clamped"},
     ["-load_end_force = 0,0,1 with -bc_end clamped: the end cannot move"]),
    ({"load_end_moment": "0,0,1", "bc_end": "clamped"},
     ["-load_end_moment = 0,0,1 with -bc_end clamped: the end cannot turn"]),
    ({"rod_shape": "circle", "load_end_force": "1,0,0"},
     ["-load_end_force = 1,0,0 on a closed ring"]),
    ({"rod_shape": "circle", "load_gravity": "0,0,-1"},
     ["-load_gravity = 0,0,-1 on a closed ring: nothing supports the rod"]),
    ({"bc_start": "free", "load_gravity": "0,0,-1"},
     ["-load_gravity = 0,0,-1 on -bc_start free and -bc_end free"]),
    ({"bc_start": "free", "load_end_moment": "0,0,1"}, ["end load with -bc_start free and "
                                                        "-bc_end free"]),
    ({"case_name": "a/b"}, ["-case_name = a/b: a case name is a plain name"]),
    ({"restart": "/nonexistent/rodsnes/dir"}, ["-restart = /nonexistent/rodsnes/dir: no such "
                                               "directory"]),
]


@pytest.mark.parametrize("d, expects", VALIDATION,
                         ids=["-".join(sorted(d)) + str(i) for i, (d, _) in enumerate(VALIDATION)])
def test_validation_errors(error, d, expects):
    msg = error(d)
    for e in expects:
        assert e in msg, msg


def test_scene_error_lists_options_and_all_problems(opts):
    opts({"rod_length": "-1", "rod_order": "7", "load_steps": "0"})
    with pytest.raises(SceneError) as ei:
        read_scene(argv=ARGV)
    assert set(ei.value.options) == {"-rod_length", "-rod_order", "-load_steps"}
    assert len(str(ei.value).splitlines()) == 3


@pytest.mark.parametrize("d", [
    {"bc_end": "sliding", "bc_end_turns": "3", "load_end_force": "0,0,-1"},
    {"bc_end": "clamped", "bc_end_turns": "-1.25"},
    {"rod_shape": "helix", "rod_helix_radius": "0.05", "rod_helix_pitch": "-0.02"},
    {"rod_shape": "circle", "rod_twist_turns": "2", "rod_arc_radius": str(1 / (2 * math.pi))},
    {"rod_shape": "arc", "rod_arc_angle": "360"},
    {"rod_shape": "straight", "rod_closed": "false"},
    {"rod_shear": "5e5", "rod_GA": "10"},   # G < E/3 is fine when nu is not needed
    {"bc_start": "free", "bc_end": "free"},
])
def test_accepted_combinations(read, d):
    read(d)


# --- shapes ---------------------------------------------------------------------
def test_circle(read):
    s = read({"rod_shape": "circle", "rod_length": "2"})
    assert s.rod.closed is True
    assert s.rod.arc_radius == pytest.approx(1 / math.pi, rel=1e-15)
    assert s.rod.arc_angle_deg == 360.0
    assert (s.bc.start, s.bc.end) == ("free", "free")


def test_arc_radius_or_angle(read, opts):
    s = read({"rod_shape": "arc", "rod_arc_radius": "2"})
    assert s.rod.arc_angle_deg == pytest.approx(math.degrees(0.5), rel=1e-14)
    assert s.rod.closed is False
    PETSc.Options().delValue("-rod_arc_radius")
    s = read({"rod_arc_angle": "90"})
    assert s.rod.arc_radius == pytest.approx(2 / math.pi, rel=1e-14)
    s = read({"rod_arc_radius": str(2 / math.pi)})       # consistent: fine
    assert s.rod.arc_angle_deg == 90.0


def test_helix(read):
    r = read({"rod_shape": "helix", "rod_helix_radius": "0.1", "rod_helix_pitch": "0.2",
              "rod_length": "3"}).rod
    assert (r.helix_radius, r.helix_pitch, r.closed) == (0.1, 0.2, False)
    assert r.helix_turns == pytest.approx(3 / math.hypot(0.2 * math.pi, 0.2), rel=1e-14)


def test_contact_options(read):
    s = read({"contact": None, "contact_penalty": "1e4", "contact_radius": "0.02",
              "contact_exclusion": "0", "rod_order": "2"})
    c = s.contact
    assert (c.enabled, c.penalty, c.radius, c.exclusion, c.quadrature) == (True, 1e4, 0.02,
                                                                           0.0, 4)
    assert s.contact_radius == 0.02
    assert read({"contact_quadrature": "7", "contact_model": "projection"}).contact.quadrature == 7
    assert s.contact.curvature is True                # the thickness bound on bending, by default
    assert read({"contact": None, "contact_curvature": "false"}).contact.curvature is False
    # a reference arc tighter than the contact radius is fine once the bound is off
    read({"rod_shape": "arc", "rod_arc_radius": "0.2", "rod_length": "0.6", "contact": None,
          "contact_radius": "0.25", "contact_curvature": "false"})
    # (an arc of nearly a turn whose ends start inside each other's tube is refused)
    with pytest.raises(SceneError, match="the arc's ends start 0.239 apart"):
        read({"rod_shape": "arc", "rod_arc_radius": "0.2", "rod_length": "1", "contact": None,
              "contact_radius": "0.25", "contact_curvature": "false"})


def test_contact_law_auto(read):
    """-contact_model auto (the default) picks the pair potential where the mesh resolves it
    (automatic points per element within contact.potential.MAX_POINTS) and the closest-point
    projection on coarser meshes or with -contact_zones; an explicit law is kept."""
    from rodsnes.contact.potential import MAX_POINTS, points_per_element
    base = {"contact": None, "contact_radius": "0.025", "rod_length": "1"}
    for n in (8, 60):
        s = read(dict(base, rod_nelem=str(n)))
        c = s.contact
        resolved = points_per_element(1.0 / n, *s.contact_law) <= MAX_POINTS
        assert resolved == (n == 60)
        assert (c.model, c.model_auto) == ("potential" if resolved else "projection", True)
    assert read(dict(base, rod_nelem="60", contact_zones="true")).contact.model == "projection"
    c = read(dict(base, rod_nelem="60", contact_model="projection")).contact
    assert (c.model, c.model_auto) == ("projection", False)


def test_the_standoff_is_refused_where_a_helix_starts_in_contact(read):
    """-contact_standoff s: the law acts from 2 a (1 + s); a reference helix whose neighbouring
    turns are closer than that, or an arc bent tighter than 1/(a (1 + s)), would be pushed
    apart unloaded, and is refused with the largest standoff it allows
    (scene.helix_turn_distance: P cos(alpha) to first order)."""
    from rodsnes.errors import SceneError
    from rodsnes.io.scene import helix_turn_distance
    R, P = 0.03, 0.0215
    t = np.linspace(-0.5, 0.5, 200001)              # x(0) to x(2 pi + t), sampled
    brute = np.sqrt((2 * R * np.sin(t / 2)) ** 2 + (P * (1 + t / (2 * np.pi))) ** 2).min()
    assert helix_turn_distance(R, P) == pytest.approx(brute, rel=1e-9)
    assert helix_turn_distance(R, P) == pytest.approx(P * R / math.hypot(R, P / (2 * math.pi)),
                                                      rel=1e-4)
    # a steep helix: the nearest point beyond the exclusion lies within the first turn
    Rs, Ps, excl = 0.005, 0.04, math.pi * 0.0112
    phi = np.linspace(0, 6 * np.pi, 600001)
    arc = phi * math.hypot(Rs, Ps / (2 * np.pi))
    d = np.sqrt((2 * Rs * np.sin(phi / 2)) ** 2 + (Ps * phi / (2 * np.pi)) ** 2)
    assert helix_turn_distance(Rs, Ps, excl) == pytest.approx(d[arc >= excl].min(), rel=1e-5)
    base = {"contact": None, "rod_radius": "0.01", "rod_shape": "helix", "rod_length": "1",
            "rod_helix_radius": str(R), "rod_helix_pitch": str(P), "rod_nelem": "100"}
    allowed = helix_turn_distance(R, P) / 0.02 - 1                    # 0.0665
    s = read(dict(base, contact_standoff="0.05"))
    assert s.contact.standoff == 0.05 and s.contact_law[0] == pytest.approx(0.0105, rel=1e-15)
    with pytest.raises(SceneError, match=r"-contact_standoff = 0.08 .*use a standoff below %.3g"
                       % allowed):
        read(dict(base, contact_standoff="0.08"))
    # a coil whose turns are no further apart than the diameter allows none
    with pytest.raises(SceneError, match=r"allows none"):
        read(dict(base, rod_helix_pitch="0.0201", contact_standoff="0.01"))
    # a reference arc bent tighter than the law's tube
    arc_opts = {"contact": None, "rod_radius": "0.01", "rod_shape": "arc",
                "rod_arc_radius": "0.0105", "rod_length": "0.0366", "rod_nelem": "8"}
    read(arc_opts)
    with pytest.raises(SceneError, match=r"folds on itself.*use a standoff below 0.05 "):
        read(dict(arc_opts, contact_standoff="0.1"))
    assert read(dict(base, contact_standoff="0")).contact.standoff == 0.0
    assert read({"contact": None}).contact.standoff == 0.0               # the default


def test_penalty_adaptation_defaults(read):
    """The promise (-contact_penetration, default 1 %) is kept by raising mu unless the user
    chose mu; an explicit -contact_penalty_adapt decides either way."""
    c = read({"contact": None}).contact
    assert (c.penetration, c.adapt) == (0.01, True)
    assert read({"contact": None, "contact_penalty": "1e4"}).contact.adapt is False
    c = read({"contact": None, "contact_penalty": "1e4", "contact_penalty_adapt": "1",
              "contact_penetration": "0.005"}).contact
    assert (c.penetration, c.adapt, c.penalty) == (0.005, True, 1e4)
    assert read({"contact": None, "contact_penalty_adapt": "false"}).contact.adapt is False


def test_output_options(read, tmp_path):
    s = read({"output_dir": "/tmp/x", "restart": str(tmp_path), "case_name": "mycase",
              "quiet": None})
    assert (s.output.dir, s.output.restart, s.output.case_name, s.output.quiet) == \
        ("/tmp/x", str(tmp_path), "mycase", True)
    assert s.given == ("case_name", "output_dir", "quiet", "restart")


# --- case name --------------------------------------------------------------------
@pytest.mark.parametrize("argv, name", [
    (["rodsnes"], "default"),
    (["rodsnes", "-options_file", "cases/plectoneme.opts"], "plectoneme"),
    (["rodsnes", "-options_file", "cases/a.opts", "-options_file", "cases/b.opts"], "b"),
    (["rodsnes", "-options_file", "cases/a.opts", "-options_file", "options/solver.opts"], "a"),
    (["rodsnes", "-options_file", "/home/u/cases/sub/ring.opts", "-options_file", "x.opts"],
     "ring"),
    (["rodsnes", "-options_file", "options/solver.opts"], "solver"),
    (["rodsnes", "-options_file", "mycases/x.opts", "-options_file", "y.txt"], "y.txt"),
    (["rodsnes", "-options_file"], "default"),
])
def test_case_name_from_argv(read, argv, name):
    s = read(argv=argv)
    assert s.output.case_name == name
    assert s.output.dir == "out/" + name


def test_case_name_option_wins(read):
    s = read({"case_name": "mine"}, argv=["rodsnes", "-options_file", "cases/a.opts"])
    assert (s.output.case_name, s.output.dir) == ("mine", "out/mine")


# --- unknown options ----------------------------------------------------------------
def _unknown(opts, d):
    db = opts(d)
    with pytest.raises(SceneError) as ei:
        check_unknown_options(db)
    return ei.value


def test_unknown_option_suggestion(opts):
    e = _unknown(opts, {"rod_lenght": "2"})
    assert str(e) == "unknown option -rod_lenght: did you mean -rod_length?"
    assert e.options == ("-rod_lenght",)


def test_all_unknown_options_listed(opts):
    e = _unknown(opts, {"rod_lenght": "2", "bc_ned": "free", "contact_pently": "1",
                        "totally_bogus": "1", "rod_zzzzzzzz": "1"})
    msg = str(e)
    assert "unknown option -rod_lenght: did you mean -rod_length?" in msg
    assert "unknown option -bc_ned: did you mean -bc_end" in msg
    assert "unknown option -contact_pently: did you mean -contact_penalty" in msg
    assert "unknown option -totally_bogus: neither a rodsnes nor a PETSc option" in msg
    assert "unknown option -rod_zzzzzzzz: not a rodsnes option" in msg
    assert [l.split(":")[0] for l in msg.splitlines()] == [
        "unknown option -" + n for n in
        ("bc_ned", "contact_pently", "rod_lenght", "rod_zzzzzzzz", "totally_bogus")]
    assert len(msg.splitlines()) == 5


def test_several_close_suggestions(opts):
    e = _unknown(opts, {"rod_EI3": "1"})
    assert str(e) == "unknown option -rod_EI3: did you mean -rod_EI, -rod_EI2 or -rod_EI1?"


def test_rodsnes_prefix_wins_over_petsc(opts):
    # starts with "rod_": must be a rodsnes option even if it looks like PETSc
    e = _unknown(opts, {"rod_snes_monitor": None})
    assert "unknown option -rod_snes_monitor" in str(e)


def test_petsc_and_rodsnes_options_not_flagged(opts):
    d = {o.name: "1" for o in scene.OPTIONS}
    d.update({"snes_monitor": None, "ksp_type": "preonly", "pc_type": "lu", "log_view": None,
              "options_left": None, "mat_mumps_icntl_14": "50", "eps_nev": "3",
              "malloc_debug": None, "help": None, "dm_view": None, "info": None})
    db = opts(d)
    check_unknown_options(db)
    check_unknown_options()   # default: global database


def test_options_of_rodsnes_own_solvers_go_to_petsc(opts):
    """-stability_ (the inertia's LDL^T), -estimate_, -planar_ and -planar_stability_ prefix
    PETSc's options of rodsnes' own solvers: accepted when a PETSc option follows, refused
    otherwise (a misspelt rodsnes option such as -stability_x is not left to PETSc)."""
    check_unknown_options(opts({"stability_mat_mumps_icntl_7": "5", "estimate_snes_max_it": "50",
                                "planar_pc_factor_mat_solver_type": "mumps",
                                "planar_stability_mat_mumps_icntl_14": "80", "stability": None}))
    for bad in ("stability_x", "estimate_foo", "planar_bogus", "planar_stability_q"):
        assert "unknown option -" + bad in str(_unknown(opts, {bad: "1"}))


# --- help --------------------------------------------------------------------------
def test_help_text_lists_every_option_once():
    text = help_text()
    for o in scene.OPTIONS:
        assert text.count("  -%s <" % o.name) == 1, o.name
    assert "  -rod_length <1.>: rod length L" in text
    assert "  -rod_radius <0.01>: " in text
    assert "  -rod_youngs <1e+06>: " in text
    assert "  -load_end_force <0.,0.,0.>: " in text
    assert "  -rod_shape <straight>: reference centreline (one of) straight arc circle helix" \
        in text
    assert "  -contact <false>: " in text
    for title in scene.SECTIONS.values():
        assert title in text
    assert len(scene.OPTIONS) == 67
    for name in scene.RETIRED:                # refused with what replaced them, never listed
        assert "-%s " % name not in text and "-%s <" % name not in text


def test_option_table_is_consistent():
    names = [o.name for o in scene.OPTIONS]
    assert len(set(n.lower() for n in names)) == len(names)
    for o in scene.OPTIONS:
        assert o.section in scene.SECTIONS
        assert o.name.startswith(scene.RODSNES_PREFIXES), o.name
