"""The seven ratings of one trial: asking them on the terminal and checking each answer.

A rating is a number on the study's scale (``study.json``'s ``scale``: 0-10 with at most one
decimal by default). :func:`ask` asks the indices one prompt at a time, asks again after a bad
answer (saying why), shows the seven at the end and asks to save them; nothing is returned (so
nothing is recorded) until all seven are given and confirmed. Ctrl-C raises KeyboardInterrupt and
the end of the input raises :class:`RatingsAbandoned`: the caller records nothing in either case.
"""
from __future__ import annotations

import math
import re

from ..analysis.scoring import INDICES
from ..base.prompt import read_line

#: What a participant reads for each index (the paper's wording, section 4.2).
LABELS = {
    "soft_tissue_material": "soft tissue material",
    "force_feedback": "force feedback performance",
    "acupuncture_effect": "acupuncture effect",
    "training_environment": "training environment",
    "real_time": "real-time",
    "training_effect": "training effect",
    "system_stability": "system stability",
}

DEFAULT_SCALE = {"min": 0, "max": 10, "decimals": 1}

_NUMBER = re.compile(r"^[+]?(\d+)(?:[.,](\d*))?$|^[+]?[.,](\d+)$")


class RatingsAbandoned(Exception):
    """The input ended before all seven ratings were given and confirmed."""


def scale_text(scale: dict) -> str:
    d = int(scale["decimals"])
    step = "whole numbers" if d == 0 else f"up to {d} decimal{'s' if d > 1 else ''}"
    return f"{scale['min']:g}-{scale['max']:g}, {step}"


def parse_score(text: str, scale: dict) -> float:
    """One answer as a rating, or ValueError saying what is wrong with it (for the re-ask)."""
    s = text.strip()
    if not s:
        raise ValueError("no answer")
    m = _NUMBER.match(s)
    if not m:
        raise ValueError(f"{s!r} is not a number")
    frac = m.group(2) if m.group(1) is not None else m.group(3)
    if frac and len(frac.rstrip("0")) > int(scale["decimals"]):
        raise ValueError(f"{s} has more decimals than the scale's {int(scale['decimals'])}")
    v = float(s.replace(",", "."))
    if not (math.isfinite(v) and float(scale["min"]) <= v <= float(scale["max"])):
        raise ValueError(f"{s} is outside {scale['min']:g}-{scale['max']:g}")
    return v


def fmt_score(v: float) -> str:
    """A rating as written to ratings.csv (``7``, ``7.5``)."""
    return f"{v:g}"


def check_row(values, scale: dict) -> list[float]:
    """Seven ratings as given on a command line or in a file: each parsed by :func:`parse_score`
    (ValueError naming the index otherwise)."""
    if len(values) != len(INDICES):
        raise ValueError(f"{len(values)} ratings given, {len(INDICES)} needed ({', '.join(INDICES)})")
    out = []
    for name, text in zip(INDICES, values):
        try:
            out.append(parse_score(str(text), scale))
        except ValueError as e:
            raise ValueError(f"{name}: {e}") from None
    return out


def ask(code: str, scale: dict, read=read_line, write=print, previous=None) -> list[float]:
    """Ask the seven ratings of system ``code``; returns them once all are given and confirmed.
    ``read(prompt)`` returns a line (EOFError at the end of the input; by default
    :func:`~haptic_acu.base.prompt.read_line`, which a Ctrl-C ends however early it comes),
    ``write(text)`` shows one.
    ``previous``: ratings already recorded (shown, for a correction)."""
    write(f"Please rate {code} on each of {len(INDICES)} points ({scale_text(scale)}; "
          f"{scale['max']:g} is best).")
    width = max(len(v) for v in LABELS.values())
    if previous is not None:
        write("Recorded so far:")
        for n, v in zip(INDICES, previous):
            write(f"  {LABELS[n]:<{width}}   {fmt_score(v)}")
    try:
        while True:
            values = []
            for k, name in enumerate(INDICES, 1):
                while True:
                    answer = read(f"  {k}/{len(INDICES)} {LABELS[name]:<{width}} : ")
                    try:
                        values.append(parse_score(answer, scale))
                        break
                    except ValueError as e:
                        write(f"    {e}; please give a number {scale_text(scale)}")
            write(f"Your ratings of {code}:")
            for n, v in zip(INDICES, values):
                write(f"  {LABELS[n]:<{width}}   {fmt_score(v)}")
            while True:
                answer = read("  Save these ratings? [y = save, n = rate again] ").strip().lower()
                if answer in ("y", "yes"):
                    return values
                if answer in ("n", "no"):
                    write("Again from the first point.")
                    break
                write("    please answer y or n")
    except EOFError:
        raise RatingsAbandoned("the input ended before the seven ratings were saved") from None
