"""Absurd config values and a UTF-8 BOM, through the real CLI: one line naming the key,
exit 2, before anything runs; the BOM is accepted as the trajectories accept it."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from haptic_acu.base.config import load_config

ROOT = Path(__file__).resolve().parent.parent
DEFAULT = (ROOT / "config" / "tissue.toml").read_text()


def with_value(section: str, key: str, value: str) -> str:
    """The default config with ``section.key`` set to ``value`` (the text, as TOML)."""
    head = DEFAULT.index(f"[{section}]")
    m = re.compile(rf"^{key}\s*=.*$", re.M).search(DEFAULT, head)
    assert m, (section, key)
    return DEFAULT[:m.start()] + f"{key} = {value}" + DEFAULT[m.end():]


def replay_with(tmp_path, text: str, name="c.toml", data=None):
    cfg = tmp_path / name
    if data is not None:
        cfg.write_bytes(data)
    else:
        cfg.write_text(text)
    return subprocess.run([sys.executable, "-m", "haptic_acu", "replay", "--config", str(cfg),
                           "--out", str(tmp_path / "out"), str(tmp_path / "missing.csv")],
                          capture_output=True, text=True, timeout=120, cwd=ROOT)


@pytest.mark.parametrize("section,key,value", [
    ("body", "fit_samples", "2000000000"),
    ("solver", "static_tolerance_um", "1e-300"),
    ("solver", "sweeps_per_tick", "1000000"),
    ("skin", "k_surface_n_per_mm", "1e300"),
    ("needle", "bone_stiffness_n_per_mm", "1e300"),
    ("safety", "force_limit_n", "1e30"),
    ("scene", "max_hand_speed_m_per_s", "1e9"),
    ("body", "fit_samples", "2e9"),  # not an integer at all
])
def test_absurd_value_one_line(tmp_path, section, key, value):
    r = replay_with(tmp_path, with_value(section, key, value))
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr
    assert f"{section}.{key}" in lines[0] and "c.toml" in lines[0]


def test_bounds_admit_the_default_and_presets():
    for p in [ROOT / "config" / "tissue.toml", *sorted((ROOT / "config").glob("presets/*.toml"))]:
        load_config(p)


def test_utf8_bom_accepted(tmp_path):
    cfg = tmp_path / "bom.toml"
    cfg.write_bytes(b"\xef\xbb\xbf" + DEFAULT.encode())
    assert load_config(cfg) == load_config(ROOT / "config" / "tissue.toml").__class__(
        **{**load_config(ROOT / "config" / "tissue.toml").__dict__, "path": str(cfg)})
    # through the CLI the config is accepted and the missing trajectory is what is reported
    r = replay_with(tmp_path, "", "bom2.toml", data=b"\xef\xbb\xbf" + DEFAULT.encode())
    assert r.returncode == 2 and "missing.csv" in r.stderr and "bom2.toml" not in r.stderr, r.stderr
