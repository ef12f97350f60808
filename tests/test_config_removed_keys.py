"""A key the model no longer reads (``needle.hole_radius_mm``: the insertion tracks decide
re-entry, their damage decaying over the needle's radius): an old config that still has it loads,
means what it meant, and says once, in one line naming the file and the key, that it is ignored."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from haptic_acu.base.config import load_config
from haptic_acu.base.errors import UserError
from haptic_acu.tissue.mechanics import overlap_damage

ROOT = Path(__file__).resolve().parent.parent
DEFAULT = ROOT / "config" / "tissue.toml"


def old_config(tmp_path, value="1.0"):
    text = DEFAULT.read_text().replace("[needle]\n", f"[needle]\nhole_radius_mm = {value}\n", 1)
    p = tmp_path / "old.toml"
    p.write_text(text)
    return p


def test_old_config_loads_with_one_warning_line_and_the_same_meaning(tmp_path, capsys):
    cfg = load_config(old_config(tmp_path))
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert "old.toml" in err[0] and "'needle.hole_radius_mm'" in err[0] and "no longer used" in err[0]
    assert "needle's radius" in err[0]  # says why
    base = load_config(DEFAULT)
    assert cfg.__class__(**{**cfg.__dict__, "path": base.path}) == base
    assert not hasattr(cfg.needle, "hole_radius_mm")


def test_any_old_value_is_ignored_not_validated(tmp_path, capsys):
    """The value is not read, so whatever an old file held (even one the old range refused) changes
    nothing; a --set of it on an old file is accepted the same way."""
    base = load_config(DEFAULT)
    for v in ("0.15", "1e9", "-3"):
        cfg = load_config(old_config(tmp_path, v), overrides=["needle.hole_radius_mm=2"])
        assert cfg.needle == base.needle
    assert capsys.readouterr().err.count("hole_radius_mm") == 3


def test_setting_it_on_a_new_config_is_an_unknown_key():
    with pytest.raises(UserError, match="--set needle.hole_radius_mm: unknown key"):
        load_config(DEFAULT, overrides=["needle.hole_radius_mm=1"])


def test_the_cli_warns_once_and_runs_on(tmp_path):
    """Through the CLI: the warning line, then the run goes on (here to the missing trajectory's
    own one-line error, exit 2)."""
    r = subprocess.run([sys.executable, "-m", "haptic_acu", "replay", "--config", str(old_config(tmp_path)),
                        "--out", str(tmp_path / "o"), str(tmp_path / "missing.csv")],
                       capture_output=True, text=True, timeout=120, cwd=ROOT)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 2 and "Traceback" not in r.stderr, r.stderr
    assert "hole_radius_mm" in lines[0] and "missing.csv" in lines[1]


def test_the_track_reach_that_replaced_it_is_the_needles_radius():
    """What replaced the key: damage is the overlap of two needle cross-sections (lens area over disc
    area, computed here independently), 1 on the track, 0 from two radii: no length of its own."""
    import math
    r = 0.125e-3
    for d in (0.0, 0.3 * r, r, 1.7 * r, 2 * r, 3 * r):
        if d >= 2 * r:
            want = 0.0
        else:  # the lens of two circles of radius r at distance d, over pi r^2
            want = (2 * r * r * math.acos(d / (2 * r)) - 0.5 * d * math.sqrt(4 * r * r - d * d)) / (math.pi * r * r)
        assert overlap_damage(d, r) == pytest.approx(want, abs=1e-12)
