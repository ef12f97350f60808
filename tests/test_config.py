"""Config loading: the default file reads as Table 2; every bad file is one line on stderr, exit 2.

Bad configs go through the real command line (``python -m haptic_acu fit --config FILE``), each a copy
of config/tissue.toml with one edit.
"""
import re
import subprocess
import sys

import pytest

from haptic_acu.base.config import DEFAULT_CONFIG, load_config


def run_fit(*args):
    return subprocess.run([sys.executable, "-m", "haptic_acu", "fit", *map(str, args)],
                          capture_output=True, text=True, timeout=120)


def assert_one_line_error(proc, *needles):
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert "Traceback" not in proc.stderr
    assert proc.stderr.endswith("\n") and proc.stderr.count("\n") == 1, repr(proc.stderr)
    for needle in needles:
        assert needle in proc.stderr, (needle, proc.stderr)


def edit(text, section, key, value=None, *, drop=False):
    """Set (or with drop=True remove) ``key`` in ``[section]`` of a TOML text; the key must exist."""
    out, current, hits = [], None, 0
    for line in text.splitlines():
        header = re.match(r"\s*\[([^\]]+)\]", line)
        if header:
            current = header.group(1).strip()
        elif current == section and re.match(rf"\s*{re.escape(key)}\s*=", line):
            hits += 1
            if drop:
                continue
            line = f"{key} = {value}"
        out.append(line)
    assert hits == 1, (section, key)
    return "\n".join(out) + "\n"


def add(text, section, line):
    """Insert ``line`` right after the ``[section]`` header."""
    assert f"[{section}]\n" in text
    return text.replace(f"[{section}]\n", f"[{section}]\n{line}\n", 1)


def drop_section(text, section):
    out, skipping = [], False
    for line in text.splitlines():
        header = re.match(r"\s*\[([^\]]+)\]", line)
        if header:
            skipping = header.group(1).strip() == section
        if not skipping:
            out.append(line)
    assert len(out) < len(text.splitlines())
    return "\n".join(out) + "\n"


BASE = DEFAULT_CONFIG.read_text()

# (case id, edited config text, the key the message must name)
BAD = [
    ("unknown key", add(BASE, "skin", "colour = 3"), "skin.colour"),
    ("unknown section", BASE + "\n[extra]\nx = 1\n", "extra"),
    ("missing key", edit(BASE, "skin", "rings", drop=True), "skin.rings"),
    ("missing section", drop_section(BASE, "safety"), "safety"),
    ("string for number", edit(BASE, "skin", "thickness_mm", '"0.8"'), "skin.thickness_mm"),
    ("float for int", edit(BASE, "skin", "rings", "8.0"), "skin.rings"),
    ("number for bool", edit(BASE, "needle", "lateral_constraint", "1"), "needle.lateral_constraint"),
    ("bool for number", edit(BASE, "fat", "k_virtual_n_per_mm", "true"), "fat.k_virtual_n_per_mm"),
    ("nan", edit(BASE, "muscle", "thickness_mm", "nan"), "muscle.thickness_mm"),
    ("short list", edit(BASE, "body", "semi_axes_mm", "[110.0, 62.0]"), "body.semi_axes_mm"),
    ("string in list", edit(BASE, "body", "semi_axes_mm", '[110.0, "62", 70.0]'), "body.semi_axes_mm[1]"),
    ("zero thickness", edit(BASE, "fat", "thickness_mm", "0.0"), "fat.thickness_mm"),
    ("negative thickness", edit(BASE, "skin", "thickness_mm", "-0.8"), "skin.thickness_mm"),
    ("zero stiffness K", edit(BASE, "muscle", "k_virtual_n_per_mm", "0.0"), "muscle.k_virtual_n_per_mm"),
    ("negative surface stiffness", edit(BASE, "skin", "k_surface_n_per_mm", "-5.0"), "skin.k_surface_n_per_mm"),
    ("rings 1", edit(BASE, "fat", "rings", "1"), "fat.rings"),
    ("rings 0", edit(BASE, "skin", "rings", "0"), "skin.rings"),
    ("lmax -1", edit(BASE, "body", "lmax", "-1"), "body.lmax"),
    ("skin coefficients missing", edit(BASE, "body", "skin_coefficients", '"nowhere.npz"'),
     "body.skin_coefficients"),
]


@pytest.mark.parametrize("text,key", [case[1:] for case in BAD], ids=[case[0] for case in BAD])
def test_bad_config_is_one_line_naming_file_and_key(tmp_path, text, key):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    assert_one_line_error(run_fit("--config", path), str(path), f"'{key}'")


def test_invalid_toml_names_file_and_line(tmp_path):
    path = tmp_path / "broken.toml"
    lines = BASE.splitlines()
    i = next(n for n, line in enumerate(lines) if re.match(r"rings\s*=", line))
    lines[i] = "rings = "
    path.write_text("\n".join(lines) + "\n")
    proc = run_fit("--config", path)
    assert_one_line_error(proc, str(path), "invalid TOML", f"line {i + 1}")


def test_missing_config_file(tmp_path):
    path = tmp_path / "no-such.toml"
    assert_one_line_error(run_fit("--config", path), str(path), "not found")


def test_default_config_is_table_2_except_where_it_says_so():
    """Zhang et al. 2021, Table 2 (thickness mm, K N/mm, d, w, L mm) in every layer, except the ring
    counts and spacings the fine-needle calibration changed (docs/model.md section 2.1), each marked
    "ours (Table 2: <the paper's value>)" on its line in config/tissue.toml."""
    cfg = load_config()
    keys = ("thickness_mm", "k_virtual_n_per_mm", "damping_n_s_per_m_per_mm", "rings", "spring_length_mm")
    table2 = {"skin": (0.8, 0.16, 3, 8, 2), "fat": (8.4, 0.08, 1, 4, 1), "muscle": (39.0, 0.23, 3, 10, 2.5)}
    comments, section = {}, None
    for line in BASE.splitlines():
        text = line.split("#", 1)[0].strip()
        if text.startswith("["):
            section = text.strip("[]")
        elif "=" in text:
            comments[(section, text.split("=", 1)[0].strip())] = line.split("#", 1)[1] if "#" in line else ""
    departures = []
    for layer in cfg.layers:
        for key, paper in zip(keys, table2[layer.name]):
            ours = getattr(layer, key)
            if ours != paper:
                assert f"ours (Table 2: {paper:g})" in comments[(layer.name, key)], (layer.name, key)
                departures.append((layer.name, key))
            else:
                assert "Table 2" in comments[(layer.name, key)], (layer.name, key)
    assert {key for _, key in departures} <= {"rings", "spring_length_mm"}  # K, d, thickness: the paper's
    assert [layer.name for layer in cfg.layers] == ["skin", "fat", "muscle"]


def test_integer_accepted_for_a_float_key(tmp_path):
    path = tmp_path / "ok.toml"
    path.write_text(edit(BASE, "muscle", "thickness_mm", "40"))
    cfg = load_config(path)
    assert cfg.muscle.thickness_mm == 40.0 and isinstance(cfg.muscle.thickness_mm, float)


def test_good_config_copy_runs(tmp_path):
    path = tmp_path / "copy.toml"
    path.write_text(BASE)
    proc = run_fit("--config", path)
    assert proc.returncode == 0, proc.stderr
    assert str(path) in proc.stdout
