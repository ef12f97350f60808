"""``--set section.key=value``: change one config key on the command line, without copying the file.

Every command that takes ``--config`` also takes ``--set`` (repeatable). The value is read as a TOML
value (``--set scene.target_depth_mm=[5,20]``, ``--set solver.servo_net='"sweeps"'``); a value that is
not valid TOML is taken as a plain string (``--set solver.servo_net=sweeps``). Overrides are applied
to the parsed TOML before it is validated, so an override is checked exactly like a key in the file
and a bad one is a one-line error naming ``--set section.key``.

:func:`haptic_acu.cli.options.add_config_args` adds both options to a sub-command's parser.
"""
from __future__ import annotations

import tomllib

from .errors import UserError

SET_HELP = ("change one config key, e.g. --set scene.target_depth_mm=[5,20] (repeatable; the value is "
            "TOML, else a string)")


def parse_set(item: str) -> tuple[str, str, object]:
    """``"section.key=value"`` -> (section, key, value). UserError on a malformed item."""
    name, sep, text = item.partition("=")
    name = name.strip()
    section, dot, key = name.partition(".")
    if not sep or not dot or not section or not key or "." in key:
        raise UserError(f"--set {item}: expected section.key=value (e.g. --set scene.target_depth_mm=[5,20])")
    text = text.strip()
    try:
        value = tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        value = text
    except ValueError:  # an integer of over 4300 digits
        raise UserError(f"--set {name}: a number of {len(text)} characters is not a value any key "
                        "takes") from None
    return section, key, value


def apply_overrides(data: dict, overrides) -> dict:
    """A copy of the parsed TOML ``data`` with each ``section.key=value`` of ``overrides`` set. A
    section or key the file does not have is an error here (the loader would call it missing or
    unknown, naming the file rather than the option)."""
    if not overrides:
        return data
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in data.items()}
    for item in overrides:
        section, key, value = parse_set(item)
        table = out.get(section)
        if not isinstance(table, dict):
            known = ", ".join(k for k, v in out.items() if isinstance(v, dict))
            raise UserError(f"--set {section}.{key}: unknown section '{section}' (known: {known})")
        if key not in table:
            raise UserError(f"--set {section}.{key}: unknown key (known: {', '.join(sorted(table))})")
        table[key] = value
    return out
