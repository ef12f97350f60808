"""The viewer's layouts: rerun blueprints, shipped as files and chosen by name.

Two layouts (docs/viewer.md says what each panel shows):

* ``trainee`` - what a trainee looks at while needling: the section through the needle's axis
  (layers, dented surfaces, needle and tip, target band, punctures, danger structures), the
  verdict line (place, depth against the target, force in words), the depth gauge, the twirl dial
  and the event log. The default for ``run`` and for ``replay --spawn/--connect``.
* ``instructor`` - the trainee's view beside the engineering plots (force in the scene frame and
  along the needle, split by layer and by part, depth against the target and the layer
  boundaries, roll and twist torque), the 3D body and the loop rates in their own tabs. The
  default for ``replay`` to a file.

Each layout is built by a function here and shipped as ``layouts/NAME.rbl`` (rerun's blueprint
file; ``python -m haptic_acu.session.blueprints`` writes them). :func:`load` reads a shipped file
by name, or any ``.rbl`` file saved from the viewer (Menu > Save blueprint), and returns something
a recording stream takes as its default blueprint.
"""
from __future__ import annotations

import sys
from pathlib import Path

import rerun.blueprint as rrb

from ..base.errors import UserError

APP_ID = "haptic-acu"
LAYOUT_DIR = Path(__file__).with_name("layouts")
LAYOUTS = ("trainee", "instructor")
DEFAULT_LIVE = "trainee"  # run, replay --spawn / --connect
DEFAULT_FILE = "instructor"  # replay to a file

# The section view's camera: straight at the plane from in front (-y), the plane's u to the right
# and +z up, far enough to show about 45 mm of tissue top to bottom (a millimetre is ~18 px in a
# 1000 px tall window). The scene under /section/scene is moved so that the point the camera looks
# at follows the needle (haptic_acu.session.trainee).
SECTION_EYE_DISTANCE_MM = 45.0
GAUGE_EYE = ((9.0, -62.0, -24.5), (9.0, 0.0, -24.5))  # the gauge's 0-50 mm, fixed


def _section_view() -> rrb.Spatial3DView:
    return rrb.Spatial3DView(
        name="needle in the tissue (section through the needle)", origin="/section",
        background=(250, 250, 250), line_grid=rrb.LineGrid3D(visible=False),
        eye_controls=rrb.EyeControls3D(position=(0.0, -SECTION_EYE_DISTANCE_MM, 0.0), look_target=(0.0, 0.0, 0.0),
                                       eye_up=(0.0, 0.0, 1.0)))


def _gauge_view() -> rrb.Spatial3DView:
    pos, target = GAUGE_EYE
    return rrb.Spatial3DView(
        name="depth gauge (mm below the skin)", origin="/gauge", background=(250, 250, 250),
        line_grid=rrb.LineGrid3D(visible=False),
        eye_controls=rrb.EyeControls3D(position=pos, look_target=target, eye_up=(0.0, 0.0, 1.0)))


def _dial_view() -> rrb.Spatial2DView:
    return rrb.Spatial2DView(name="twirl (seen from the handle)", origin="/twirl/dial", background=(250, 250, 250),
                             visual_bounds=rrb.VisualBounds2D(x_range=(-1.6, 1.6), y_range=(-1.5, 1.7)))


def trainee_container() -> rrb.Horizontal:
    """The trainee's panels (also the left half of the instructor's layout)."""
    return rrb.Horizontal(
        _section_view(),
        rrb.Vertical(
            rrb.TextDocumentView(name="verdict", origin="/verdict"),
            rrb.Horizontal(_gauge_view(), _dial_view(), column_shares=[1, 1]),
            rrb.TextLogView(name="events", origin="/events"),
            row_shares=[3, 5, 2],
        ),
        column_shares=[3, 2],
        name="trainee",
    )


def _plot(name: str, origin: str, corner=None, y_range=None) -> rrb.TimeSeriesView:
    """A plot whose legend sits where its data usually is not: the top right (the session's end,
    the needle out and the force back at zero) unless ``corner`` says otherwise."""
    return rrb.TimeSeriesView(name=name, origin=origin, plot_legend=rrb.PlotLegend(corner or rrb.Corner2D.RightTop),
                              axis_y=rrb.ScalarAxis(range=y_range) if y_range else None)


def engineering_plots() -> rrb.Vertical:
    return rrb.Vertical(
        _plot("force on the needle (N): along it (+ pushes it back), across it, scene components", "/force/total"),
        _plot("force along the needle by layer (N, + pushes the needle back)", "/force/layer"),
        _plot("force along the needle by part (N, + pushes the needle back)", "/force/part"),
        # the depth drawn down to -75 mm: the legend sits below the bone's surface (48 mm at the acupoint)
        _plot("tip depth (mm below the skin, drawn downward) with the target and the layer boundaries", "/depth",
              corner=rrb.Corner2D.LeftBottom, y_range=(-75.0, 10.0)),
        _plot("roll (deg, + clockwise seen from the handle) and twist torque (N*mm)", "/twirl/series"),
        row_shares=[3, 2, 2, 4, 2],
        name="plots",
    )


def trainee() -> rrb.Blueprint:
    return rrb.Blueprint(
        trainee_container(),
        rrb.BlueprintPanel(state="hidden"), rrb.SelectionPanel(state="hidden"),
        rrb.TimePanel(state="collapsed", timeline="sim_time"),
    )


def instructor() -> rrb.Blueprint:
    return rrb.Blueprint(
        rrb.Horizontal(
            trainee_container(),
            rrb.Tabs(
                engineering_plots(),
                rrb.Spatial3DView(name="3D body", origin="/world"),
                rrb.Vertical(_plot("loop rates (Hz)", "/rates"), rrb.TextDocumentView(name="session", origin="/session"),
                             name="loop rates", row_shares=[3, 1]),
                active_tab=0,
            ),
            column_shares=[3, 2],
        ),
        rrb.BlueprintPanel(state="hidden"), rrb.SelectionPanel(state="hidden"),
        rrb.TimePanel(state="collapsed", timeline="sim_time"),
    )


BUILDERS = {"trainee": trainee, "instructor": instructor}


def path_of(name: str) -> Path:
    return LAYOUT_DIR / f"{name}.rbl"


class FileBlueprint:
    """A blueprint read from an ``.rbl`` file, usable wherever rerun takes a default blueprint
    (its chunks are replayed into the blueprint stream rerun creates for it)."""

    def __init__(self, path: Path):
        from rerun.chunk import RrdReader

        self.path = Path(path)
        try:
            reader = RrdReader(self.path)
            stores = reader.blueprints()
            self.chunks = list(reader.stream(store=stores[0]).to_chunks()) if stores else []
        except Exception as e:  # rerun raises its own errors for a file it cannot read
            raise UserError(f"{self.path}: not a rerun blueprint file ({e})".splitlines()[0]) from None
        if not self.chunks:
            raise UserError(f"{self.path}: not a rerun blueprint file (no blueprint in it)")

    def to_blueprint(self) -> "FileBlueprint":
        return self

    def _log_to_stream(self, stream) -> None:
        import rerun as rr

        rr.send_chunks(self.chunks, recording=stream)


def load(name_or_path: str) -> FileBlueprint:
    """A bundled layout by name (``trainee``, ``instructor``) or an ``.rbl`` file by path."""
    if name_or_path in BUILDERS:
        return FileBlueprint(path_of(name_or_path))
    p = Path(name_or_path)
    if p.suffix == ".rbl":
        if not p.is_file():
            raise UserError(f"--layout {name_or_path}: no such file")
        return FileBlueprint(p)
    raise UserError(f"--layout {name_or_path!r}: give {' or '.join(LAYOUTS)}, or a blueprint file NAME.rbl")


def views(source) -> list[dict]:
    """The views of a blueprint, read back through rerun: ``source`` an .rbl or .rrd path or an
    ``RrdReader``. Each view: ``{"origin", "kind", "name"}`` (kind: rerun's class identifier, e.g.
    ``Spatial3D``, ``TimeSeries``)."""
    from rerun.chunk import RrdReader

    reader = source if isinstance(source, RrdReader) else RrdReader(str(source))
    out = []
    for entry in reader.blueprints():
        for chunk in reader.stream(store=entry).to_chunks():
            rb = chunk.to_record_batch()
            if "ViewBlueprint:space_origin" not in rb.schema.names:
                continue
            for origin, kind, name in zip(rb.column("ViewBlueprint:space_origin").to_pylist(),
                                          rb.column("ViewBlueprint:class_identifier").to_pylist(),
                                          rb.column("ViewBlueprint:display_name").to_pylist()):
                out.append({"origin": _one(origin), "kind": _one(kind), "name": _one(name)})
    return out


def _one(v):
    return v[0] if isinstance(v, list) else v


def view_origins(source) -> dict:
    """origin -> kind of every view in a blueprint (see :func:`views`)."""
    return {v["origin"]: v["kind"] for v in views(source)}


def write_all(out_dir: Path = LAYOUT_DIR) -> list[Path]:
    """Build every layout and save it as ``out_dir/NAME.rbl``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, build in BUILDERS.items():
        p = out_dir / f"{name}.rbl"
        build().save(APP_ID, str(p))
        paths.append(p)
    return paths


if __name__ == "__main__":
    for p in write_all(Path(sys.argv[1]) if len(sys.argv) > 1 else LAYOUT_DIR):
        print(p)
