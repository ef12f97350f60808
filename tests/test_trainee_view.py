"""The trainee's view without a session: the layouts (built and shipped blueprint files, read back
through rerun), the section's geometry against the body's own surfaces and closed forms, the
danger-structure hook, and the verdict's words."""
from __future__ import annotations

import numpy as np
import pytest

from haptic_acu.base.config import load_config
from haptic_acu.base.errors import UserError
from haptic_acu.servo import samples as S
from haptic_acu.session import blueprints as B
from haptic_acu.session import verdict as V
from haptic_acu.session.section import Section, Structure, patch_dent, skin_entry, structure_outline
from haptic_acu.tissue.body import Tissue

C = S.COL


@pytest.fixture(scope="module")
def tissue():
    return Tissue.from_config(load_config())


# -- layouts ------------------------------------------------------------------------------------

TRAINEE_VIEWS = {"/section": "3D", "/gauge": "3D", "/twirl/dial": "2D", "/verdict": "TextDocument",
                 "/events": "TextLog"}
PLOTS = {"/force/total", "/force/layer", "/force/part", "/depth", "/twirl/series", "/rates"}


@pytest.mark.parametrize("name", B.LAYOUTS)
def test_shipped_layout_files_are_the_built_layouts(name, tmp_path):
    """Each bundled .rbl holds the views its builder makes today (regenerate with
    `python -m haptic_acu.session.blueprints`)."""
    B.BUILDERS[name]().save(B.APP_ID, str(tmp_path / "x.rbl"))
    key = lambda vs: sorted((v["origin"], v["kind"], v["name"]) for v in vs)  # noqa: E731
    assert key(B.views(B.path_of(name))) == key(B.views(tmp_path / "x.rbl"))


def test_trainee_and_instructor_views():
    trainee = B.view_origins(B.path_of("trainee"))
    assert trainee == TRAINEE_VIEWS  # no engineering plot in the trainee's layout
    instructor = B.view_origins(B.path_of("instructor"))
    assert TRAINEE_VIEWS.items() <= instructor.items()
    assert PLOTS <= set(instructor) and all(instructor[p] == "TimeSeries" for p in PLOTS)
    names = {v["origin"]: v["name"] for v in B.views(B.path_of("instructor"))}
    for p in ("/force/total", "/force/layer", "/force/part", "/rates"):
        assert "(N" in names[p] or "(Hz)" in names[p], names[p]  # every plot names its unit
    assert "(mm" in names["/depth"] and "(deg" in names["/twirl/series"]


def test_load_by_name_or_file_and_bad_names(tmp_path):
    assert B.load("trainee").chunks
    p = tmp_path / "mine.rbl"
    B.trainee().save(B.APP_ID, str(p))
    assert B.load(str(p)).chunks
    with pytest.raises(UserError, match="give trainee or instructor"):
        B.load("nurse")
    with pytest.raises(UserError, match="no such file"):
        B.load(str(tmp_path / "none.rbl"))
    bad = tmp_path / "bad.rbl"
    bad.write_text("not a blueprint")
    with pytest.raises(UserError, match="not a rerun blueprint file") as e:
        B.load(str(bad))
    assert "\n" not in str(e.value)


# -- the section's geometry ---------------------------------------------------------------------

def test_vertical_section_meets_the_body_where_the_body_says(tissue):
    s = Section.through(tissue, [0.0, 0.0, -1.0], [0.0, 0.0, 0.01])
    np.testing.assert_allclose(s.normal, [0.0, 1.0, 0.0])
    u = np.linspace(-20.0, 20.0, 9)
    for k in range(4):
        w = s.boundary(k, u)
        p = s.to_scene(u, w)
        d = p - tissue.centre
        r = np.linalg.norm(d, axis=1)
        th = np.arccos(d[:, 2] / r)
        ph = np.arctan2(d[:, 1], d[:, 0])
        np.testing.assert_allclose(r, tissue.radius(k, th, ph), atol=1e-9)  # on boundary k
    np.testing.assert_allclose(s.boundary(0, np.zeros(1)), [0.0], atol=1e-9)  # the acupoint
    entry = skin_entry(tissue, [0.0, 0.0, -0.01], [0.0, 0.0, -1.0])
    np.testing.assert_allclose(entry, [0.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(s.depths_along(entry, [0.0, 0.0, -1.0]), tissue.depths_at_acupoint() * 1e3, atol=1e-6)


def test_oblique_section_holds_the_needle_and_its_depths_grow(tissue):
    a = np.array([np.sin(np.radians(30.0)), 0.0, -np.cos(np.radians(30.0))])
    tip = np.array([0.003, 0.0, -0.004])
    s = Section.through(tissue, a, tip)
    assert abs(np.dot(s.normal, a)) < 1e-12  # the axis lies in the plane
    np.testing.assert_allclose(s.to_scene(*s.to_uw(tip)), tip, atol=1e-12)
    entry = skin_entry(tissue, tip, a)
    d = s.depths_along(entry, a)
    d0 = tissue.depths_at_acupoint() * 1e3
    # the layers, near-parallel to the skin, are crossed at 30 deg: about 1/cos(30) longer
    np.testing.assert_allclose(d[1:3] / d0[1:3], 1.0 / np.cos(np.radians(30.0)), rtol=0.03)


def test_dent_moves_the_surface_in_by_the_dent(tissue):
    from haptic_acu.session.engine import PATCH_GRID

    th, ph = PATCH_GRID
    axes = (th[:, 0], ph[0])
    dent = 1e-3 * np.cos(th / th.max() * np.pi / 2)  # 1 mm at the pole, none at the patch's edge
    s = Section.through(tissue, [0.0, 0.0, -1.0], [0.0, 0.0, 0.0])
    u = np.array([0.0, 3.0, 8.0])
    rest = s.boundary(0, u)
    pressed = s.boundary(0, u, dent=lambda t, p: patch_dent(dent, *axes, t, p))
    want = patch_dent(dent, *axes, np.arcsin(u / 70.0), np.zeros(3)) * 1e3  # radial ~ vertical near the pole
    np.testing.assert_allclose(rest - pressed, want, rtol=0.02, atol=2e-3)
    assert rest[0] - pressed[0] == pytest.approx(1.0, abs=0.01)


def test_patch_dent_interpolates_linear_fields_exactly():
    th_axis = (np.arange(24) + 0.5) * 0.5 / 24
    ph_axis = np.arange(48) * 2 * np.pi / 48
    T, P = np.meshgrid(th_axis, ph_axis, indexing="ij")
    f = 2.0 * T + 0.1
    th = np.array([0.05, 0.123, 0.4])
    np.testing.assert_allclose(patch_dent(f, th_axis, ph_axis, th, np.array([0.3, 2.0, 6.2])), 2.0 * th + 0.1)
    assert patch_dent(f, th_axis, ph_axis, np.array([0.6]), np.zeros(1))[0] == 0.0  # past the patch


def test_danger_structures_cut_by_the_section(tissue):
    s = Section.through(tissue, [0.0, 0.0, -1.0], [0.0, 0.0, 0.0])  # the x-z plane
    # a membrane across the needle 37 mm deep: a horizontal line at w = -37
    line = structure_outline(Structure("pleura", "membrane", np.array([0.0, 0.0, -0.037]),
                                       normal=np.array([0.0, 0.0, 1.0])), s)
    np.testing.assert_allclose(line[:, 1], -37.0, atol=1e-9)
    assert line[:, 0].min() < -10 and line[:, 0].max() > 10
    # an artery of radius 2 mm running across the plane (along y), 20 mm deep, 5 mm aside: a circle
    tube = structure_outline(Structure("artery", "artery", np.array([0.005, 0.01, -0.02]), radius_m=0.002,
                                       along=np.array([0.0, 1.0, 0.0])), s)
    np.testing.assert_allclose(np.hypot(tube[:, 0] - 5.0, tube[:, 1] + 20.0), 2.0, atol=1e-9)
    # a tube at 45 deg to the plane: an ellipse, 2 mm across and 2 * sqrt(2) mm along its slant
    slant = structure_outline(Structure("nerve", "nerve", np.array([0.0, 0.0, -0.02]), radius_m=0.002,
                                        along=np.array([0.0, 1.0, 1.0]) / np.sqrt(2)), s)
    assert np.ptp(slant[:, 0]) == pytest.approx(4.0, abs=0.02)
    assert np.ptp(slant[:, 1]) == pytest.approx(4.0 * np.sqrt(2), abs=0.02)
    # a ball 1 mm off the plane with radius 2 mm: a circle of radius sqrt(3) mm; 3 mm off: missed
    ball = structure_outline(Structure("b", "vessel", np.array([0.0, 0.001, -0.01]), radius_m=0.002), s)
    np.testing.assert_allclose(np.hypot(ball[:, 0], ball[:, 1] + 10.0), np.sqrt(3.0), atol=1e-9)
    assert structure_outline(Structure("b", "vessel", np.array([0.0, 0.003, -0.01]), radius_m=0.002), s) is None


# -- the verdict's words ------------------------------------------------------------------------

def _row(layer=-1, state=0, depth_skin_mm=0.0, f=(0.0, 0.0, 0.0), axis=(np.nan, np.nan, np.nan), roll=0.0):
    r = np.zeros(S.NCOL)
    r[C["layer"]] = layer
    r[C["state_skin"]] = state
    r[C["depth_skin_m"]] = depth_skin_mm * 1e-3
    r[C["fx_n"]:C["fz_n"] + 1] = f
    r[C["axis_x"]:C["axis_z"] + 1] = axis
    r[C["roll_deg"]] = roll
    return r


@pytest.mark.parametrize("layer,depth,want", [
    (1, 6.0, "9.0 mm to go to the target"), (2, 15.0, "in range"), (2, 30.0, "in range"),
    (2, 33.2, "past the target by 3.2 mm"), (3, 48.0, "on bone: withdraw")])
def test_depth_words(layer, depth, want):
    r = _row(layer=layer, depth_skin_mm=depth)
    assert V.depth_words(r, V.needle_depth_mm(r, -99.0), (15.0, 30.0)) == want


def test_place_and_pressing():
    assert V.place(_row()) == "in the air"
    r = _row(state=1)
    assert V.place(r) == "pressing the skin"
    assert V.depth_words(r, V.needle_depth_mm(r, 0.84), (15, 30)) == "skin pressed in 0.8 mm, not yet through"
    assert V.depth_words(_row(), -3.0, (15, 30)) == "3.0 mm above the skin"
    assert [V.place(_row(layer=k)) for k in range(4)] == ["in skin", "in fat", "in muscle", "on bone"]


def test_force_sign_in_words_follows_the_needle_axis():
    down = (0.0, 0.0, -1.0)
    assert V.force_words(*V.axial_force(_row(f=(0.0, 0.0, 1.42), axis=down))) == "1.42 N pushing the needle back"
    assert V.force_words(*V.axial_force(_row(f=(0.0, 0.0, -0.31), axis=down))) == "0.31 N pulling the needle in"
    # an oblique needle pushed back along its own axis, with a sideways part
    a = np.array([np.sin(0.5), 0.0, -np.cos(0.5)])
    f = -a * 2.0 + np.array([0.0, 0.3, 0.0])
    assert V.force_words(*V.axial_force(_row(f=f, axis=a))) == "2.00 N pushing the needle back, 0.30 N sideways"
    assert V.force_words(*V.axial_force(_row())) == "none along the needle"


def test_verdict_markdown_headline():
    text = V.verdict_markdown(_row(layer=2, state=2, depth_skin_mm=33.2, f=(0, 0, 0.8), axis=(0, 0, -1), roll=90.0),
                              33.2, (15.0, 30.0), last_event="muscle punctured, 1.10 N at 9.6 mm")
    lines = text.splitlines()
    assert lines[0] == "## Tip in muscle: past the target by 3.2 mm"
    assert "**Depth 33.2 mm** along the needle (target 15-30 mm)" in lines
    assert "**Force: 0.80 N pushing the needle back**" in lines
    assert any(s.startswith("Roll +90 deg (clockwise seen from the handle)") for s in lines)
    assert lines[-1] == "Last: muscle punctured, 1.10 N at 9.6 mm"


def test_a_pressed_surface_passes_through_the_tip():
    from haptic_acu.session.trainee import PRESS_HALF_WIDTH_MM, press_through

    u = np.linspace(-10.0, 10.0, 81)
    w = -0.1 * np.abs(u) - 9.2  # a surface with a shallow smoothed dent
    out = press_through(u, w, (1.0, -12.0))
    assert np.interp(1.0, u, out) == pytest.approx(-12.0, abs=1e-12)  # through the tip
    far = np.abs(u - 1.0) >= PRESS_HALF_WIDTH_MM
    assert np.array_equal(out[far], w[far]) and np.all(out <= w)
    assert np.array_equal(press_through(u, w, (1.0, -5.0)), w)  # a tip above the surface moves nothing


def test_structures_from_the_servos_danger_rows(tissue):
    """The servo's danger rows (haptic_acu.servo.danger.DANGER's fields) as drawable structures: a
    membrane 37 mm along -z, an artery of radius 1.5 mm across the x-z plane, an empty row."""
    from haptic_acu.session.section import structures_from_danger

    dt = np.dtype([("kind", "i8"), ("p", "f8", 3), ("n", "f8", 3), ("depth", "f8"), ("radius", "f8")])
    rows = np.zeros(3, dt)
    rows[0] = (1, (0, 0, 0), (0, 0, -1), 0.037, 0.0)
    rows[1] = (4, (0.004, 0.0, -0.02), (0, 1, 0), 0.0, 0.0015)
    got = structures_from_danger(rows, names=["pleura", "posterior tibial artery"])
    assert [(s.name, s.kind) for s in got] == [("pleura", "membrane"), ("posterior tibial artery", "artery")]
    s = Section.through(tissue, [0.0, 0.0, -1.0], [0.0, 0.0, 0.0])
    np.testing.assert_allclose(structure_outline(got[0], s)[:, 1], -37.0, atol=1e-9)
    ring = structure_outline(got[1], s)
    np.testing.assert_allclose(np.hypot(ring[:, 0] - 4.0, ring[:, 1] + 20.0), 1.5, atol=1e-9)


@pytest.mark.parametrize("cmd", ["replay", "run"])
def test_a_bad_layout_is_one_line_and_exit_2(cmd, tmp_path, capsys):
    from haptic_acu.cli import main

    extra = ["--device", "scripted", "--trajectory", "default", "--rrd"] if cmd == "run" else []
    for bad, words in (("nurse", "give trainee or instructor"), (str(tmp_path / "x.rbl"), "no such file")):
        assert main([cmd, *extra, "--layout", bad, "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err.strip()
        assert words in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "out").exists()


def test_structures_from_a_points_anatomy(tissue):
    from haptic_acu.session.section import structures_from_anatomy
    from haptic_acu.tissue.patient import PlacedStructure

    class Anatomy:
        structures = [PlacedStructure("pleura", "membrane", 20.0, toward=(0.0, 0.0, -1.0)),
                      PlacedStructure("median nerve", "nerve", 12.0, centre_mm=(2.0, 0.0, -12.0), axis=(0.0, 1.0, 0.0),
                                      radius_mm=1.42)]

    got = structures_from_anatomy(Anatomy())
    s = Section.through(tissue, [0.0, 0.0, -1.0], [0.0, 0.0, 0.0])
    np.testing.assert_allclose(structure_outline(got[0], s)[:, 1], -20.0, atol=1e-9)
    ring = structure_outline(got[1], s)
    np.testing.assert_allclose(np.hypot(ring[:, 0] - 2.0, ring[:, 1] + 12.0), 1.42, atol=1e-9)


# -- frames a batch at once ---------------------------------------------------------------------

def test_a_stack_of_dents_gives_each_dents_curve(tissue):
    """patch_dent and Section.boundary on a stack of dents: each row exactly what that dent alone gives."""
    from haptic_acu.session.engine import PATCH_GRID

    th, ph = PATCH_GRID
    axes = (th[:, 0], ph[0])
    rng = np.random.default_rng(3)
    dents = rng.uniform(0.0, 1e-3, (3,) + th.shape)
    s = Section.through(tissue, [0.1, 0.0, -1.0], [0.0, 0.0, 0.0])
    u = np.linspace(-30.0, 30.0, 25)
    rest = s.boundary(1, u)
    stacked = s.boundary(1, u, start=np.tile(rest, (3, 1)), dent=lambda t, p: patch_dent(dents, *axes, t, p))
    for j in range(3):
        alone = s.boundary(1, u, start=rest, dent=lambda t, p: patch_dent(dents[j], *axes, t, p))
        np.testing.assert_array_equal(stacked[j], alone)
        assert np.nanmax(rest - alone) > 0.1  # pressed in, by a tenth of a millimetre or more
    t = rng.uniform(0.0, 0.6, (3, 7))  # inside the pole row, across the patch and past it
    p = rng.uniform(-7.0, 7.0, (3, 7))
    for j in range(3):
        np.testing.assert_array_equal(patch_dent(dents, *axes, t, p)[j], patch_dent(dents[j], *axes, t[j], p[j]))


def test_rows_added_at_once_are_the_rows_added_one_by_one():
    """Columns.add_rows keeps and sends what Columns.add row by row keeps and sends: a row whose key
    is the last kept one's is dropped, across calls too."""
    import rerun as rr

    from haptic_acu.session.trainee import Columns, row_keys

    class Rec:
        def __init__(self):
            self.sent = []

        def send_columns(self, path, indexes, columns):
            self.sent.append((path, [(i.timeline_name(), i.as_arrow_array().to_pylist()) for i in indexes],
                              [c.as_arrow_array().to_pylist() for c in columns]))

    rng = np.random.default_rng(1)
    t = [0.01 * i for i in range(9)]
    tick = list(range(0, 90, 10))
    pos = np.round(rng.normal(size=(9, 3)), 1)
    pos[3] = pos[2]  # repeats, dropped
    pos[4] = pos[2]
    labels = [f"p{i}" for i in range(9)]
    strips = rng.normal(size=(9, 2, 3))
    one, many = Rec(), Rec()
    a = {"p": Columns(rr.Points3D, partitioned=True), "s": Columns(rr.LineStrips3D, partitioned=True),
         "v": Columns(rr.TextDocument)}
    b = {"p": Columns(rr.Points3D, partitioned=True), "s": Columns(rr.LineStrips3D, partitioned=True),
         "v": Columns(rr.TextDocument)}
    keys = row_keys(np.round(pos, 3))
    texts = ["same" if i in (5, 6) else f"text {i // 2}" for i in range(9)]
    for i in range(9):
        a["p"].add(t[i], tick[i], key=keys[i], positions=pos[i:i + 1], labels=[labels[i]])
        a["s"].add(t[i], tick[i], key=keys[i], strips=[strips[i]])
        a["v"].add(t[i], tick[i], key=texts[i], text=texts[i])
    for lo, hi in ((0, 3), (3, 9)):  # two calls: the first row of the second is held against the first's last
        sl = slice(lo, hi)
        b["p"].add_rows(t[sl], tick[sl], keys[sl], positions=pos[sl], labels=labels[sl])
        b["s"].add_rows(t[sl], tick[sl], keys[sl], strips=strips[sl])
        b["v"].add_rows(t[sl], tick[sl], texts[sl], text=texts[sl])
    for name in a:
        a[name].send(one, name)
        b[name].send(many, name)
    assert one.sent == many.sent
    assert [len(x[1][0][1]) for x in one.sent] == [7, 7, 6]  # rows kept: 9 less the two repeats; texts 6
