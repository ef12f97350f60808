"""The debrief: what a trainee and an instructor read after a session, in plain words.

:func:`debrief` turns a session's summary (``summary.json``: its punctures and its ``metrics``,
:mod:`haptic_acu.analysis.metrics`) into findings per insertion, each with a severity, worst
first, and the one thing to change next time. It computes nothing from samples: every number it
names is the summary's, so the text, ``debrief.md`` and the JSON agree.

Severities: ``danger`` (the tip on bone, the device held at its force limit, the whole needle in
the tissue), ``fault`` (the depth outside the target, the entry or the angle off, one-way winding),
``note`` (what was done: twirling, lift-thrust, the technique label and why), ``good`` (what was
right). Within an insertion findings go danger, fault, note, good; insertions go by their worst
finding, then in order.

What was asked: the depth range ``scene.target_depth_mm``, the acupoint (entry offset 0) and a
perpendicular insertion (angle 0). The tolerances below are ours (no source gives a number):

* :data:`ENTRY_TOLERANCE_MM` 2 mm: an acupoint is located to a few millimetres by palpation and
  proportional (cun) measure;
* :data:`ANGLE_TOLERANCE_DEG` 10 deg: a perpendicular insertion held by hand;
* :data:`WINDING_DEG` 180 deg: a net roll of half a turn one way winds the tissue round the shaft
  (Langevin et al. 2001: unidirectional rotation grips the needle 2.67x harder than none, 1.52x
  for back-and-forth rotation); the debrief then gives the net turns.

The technique label (:mod:`haptic_acu.analysis.technique`) is withheld by the metrics for an
insertion whose tip touched bone or whose force was held at the device's limit: those strokes felt
the bone or the limit, not the tissue. The debrief says so instead of a label.
"""
from __future__ import annotations

import shutil
import textwrap

ENTRY_TOLERANCE_MM = 2.0
ANGLE_TOLERANCE_DEG = 10.0
WINDING_DEG = 180.0
FULLY_IN_MM = 0.005  # a needle this close to its whole length in the tissue has its handle on the skin
SEVERITIES = ("danger", "fault", "note", "good")
_RANK = {s: i for i, s in enumerate(SEVERITIES)}


def _f(x, nd: int = 1) -> str:
    """A number at ``nd`` decimals without a trailing ``.0`` for whole numbers at nd=1."""
    s = f"{x:.{nd}f}"
    return s[:-2] if nd == 1 and s.endswith(".0") else s


def _finding(severity: str, text: str, change: str | None = None) -> dict:
    out = {"severity": severity, "text": text}
    if change:
        out["change"] = change
    return out


def _depth(m: dict, target, needle_mm) -> list[dict]:
    lo, hi = target
    d = m.get("max_depth_mm")
    if d is None:
        return []
    out = []
    if needle_mm is not None and (m.get("needle_fully_in") or d >= needle_mm - FULLY_IN_MM):
        out.append(_finding("danger", f"the whole {_f(needle_mm)} mm needle went in: the handle met the skin",
                            "stop well before the handle reaches the skin; never sink the whole shaft"))
    if d > hi:
        out.append(_finding("fault", f"needle {_f(d, 2)} mm deep: {_f(d - hi, 2)} mm past the {_f(hi)} mm limit",
                            f"stop at {_f(lo)}-{_f(hi)} mm: watch the depth and slow down as you near {_f(hi)} mm"))
    elif d < lo:
        out.append(_finding("fault", f"needle {_f(d, 2)} mm deep: {_f(lo - d, 2)} mm short of the {_f(lo)} mm target",
                            f"go on to {_f(lo)}-{_f(hi)} mm before manipulating"))
    else:
        out.append(_finding("good", f"needle {_f(d, 2)} mm deep, within the {_f(lo)}-{_f(hi)} mm target"))
    return out


def _contact(m: dict, force_limit_n) -> list[dict]:
    out = []
    bone = m.get("time_on_bone_s") or 0.0
    held = m.get("time_at_force_limit_s") or 0.0
    if bone > 0:
        out.append(_finding("danger", f"the tip was on bone for {bone:.2f} s",
                            "when the resistance turns hard and does not give, stop and withdraw a little: "
                            "that is bone"))
    if held > 0:
        lim = f" ({force_limit_n:g} N)" if force_limit_n else ""
        out.append(_finding("danger", f"the force was held at the device's limit{lim} for {held:.2f} s: "
                            "what you felt then was the device, not the tissue",
                            "ease off as soon as the force stops rising with depth"))
    return out


def _entry(m: dict) -> list[dict]:
    out = []
    off, ang = m.get("entry_offset_mm"), m.get("angle_deg")
    if off is not None:
        if off > ENTRY_TOLERANCE_MM:
            out.append(_finding("fault", f"entry {off:.2f} mm off the acupoint (asked: on it, within "
                                f"{_f(ENTRY_TOLERANCE_MM)} mm)", "place the tip on the acupoint before you press"))
        else:
            out.append(_finding("good", f"entry {off:.2f} mm from the acupoint"))
    if ang is not None:
        if ang > ANGLE_TOLERANCE_DEG:
            out.append(_finding("fault", f"inserted at {ang:.1f} deg to the skin's normal (asked: perpendicular, "
                                f"within {_f(ANGLE_TOLERANCE_DEG)} deg)", "hold the needle upright as it enters"))
        else:
            out.append(_finding("good", f"inserted at {ang:.1f} deg to the normal (perpendicular asked)"))
    return out


def _twirl(m: dict) -> list[dict]:
    tw = (m.get("technique") or {}).get("twirl") or {}
    out = []
    net = tw.get("net_rotation_deg") or 0.0
    if tw.get("cycles"):
        swing = tw.get("swing_deg")
        frq = tw.get("frequency_hz")
        s = f"{tw['cycles']} twirl cycle{'s' if tw['cycles'] != 1 else ''}"
        if swing is not None:
            s += f", {swing:.0f} deg swing (peak to peak)"
        if frq is not None:
            s += f" at {frq:.2f} Hz"
        out.append(_finding("note", s))
    if abs(net) >= WINDING_DEG:
        way = "clockwise" if net > 0 else "counter-clockwise"
        out.append(_finding("fault", f"one-way winding: the needle turned {abs(net):.0f} deg net {way} "
                            f"({abs(net) / 360.0:.2f} turns); tissue wound round the shaft grips it "
                            "(a stuck needle)", "twirl back and forth evenly, and unwind before you withdraw"))
    return out


def _lift_thrust(m: dict) -> list[dict]:
    lt = m.get("lift_thrust") or {}
    if not lt.get("cycles"):
        return []
    s = f"{lt['cycles']} lift-thrust cycle{'s' if lt['cycles'] != 1 else ''}"
    if lt.get("mean_amplitude_mm") is not None:
        s += f", {lt['mean_amplitude_mm']:.2f} mm amplitude"
    if lt.get("frequency_hz") is not None:
        s += f" at {lt['frequency_hz']:.2f} Hz"
    return [_finding("note", s)]


def _technique(m: dict) -> list[dict]:
    cl = (m.get("technique") or {}).get("classification") or {}
    if cl.get("withheld"):
        return [_finding("note", f"no technique label: {cl['withheld']}")]
    label = cl.get("label")
    if not label:
        return []
    why = []
    inp = cl.get("inputs") or {}
    rule = cl.get("rule") or {}
    if cl.get("twirl_vote"):
        why.append(f"twirling votes {cl['twirl_vote']} ({inp.get('swing_deg', 0):.0f} deg swing at "
                   f"{inp.get('frequency_hz', 0):.2f} Hz; small <= {rule.get('small_swing_deg', 90):g} deg and "
                   f"slow <= {rule.get('slow_hz', 1):g} Hz reinforce, large >= {rule.get('large_swing_deg', 180):g} "
                   f"deg and fast >= {rule.get('fast_hz', 2):g} Hz reduce)")
    if cl.get("lift_thrust_vote"):
        r = inp.get("thrust_to_lift")
        heavy = rule.get("heavy_ratio", 1.25)
        why.append(f"lift-thrust votes {cl['lift_thrust_vote']} (thrust/lift resistance "
                   f"{'-' if r is None else f'{r:.2f}'}; >= {heavy:g} reinforces, <= {1 / heavy:.2f} reduces)")
    return [_finding("note", f"technique: {label}" + (": " + "; ".join(why) if why else ""))]


def insertion_findings(m: dict, target, needle_mm=None, force_limit_n=None) -> list[dict]:
    """One insertion's findings (``per_insertion`` entry ``m``), worst first."""
    f = _contact(m, force_limit_n) + _depth(m, target, needle_mm) + _entry(m) + _twirl(m) + _lift_thrust(m)
    f += _technique(m)
    return sorted(f, key=lambda x: _RANK[x["severity"]])  # stable: the order above within a severity


def debrief(summary: dict, force_limit_n: float | None = None, needle_length_mm: float | None = None) -> dict:
    """The debrief of a session summary: ``{"insertions": [{"insertion": n, "worst": severity,
    "findings": [...], "change": text or None}, ...] (worst first), "change": the session's one
    thing to change (the worst insertion's) or None, "headline": one sentence}``."""
    m = summary.get("metrics") or {}
    target = tuple(m.get("target_depth_mm") or (0.0, 0.0))
    needle_length_mm = needle_length_mm if needle_length_mm is not None else summary.get("needle_length_mm")
    force_limit_n = force_limit_n if force_limit_n is not None else summary.get("force_limit_n")
    ins = []
    for n, pi in enumerate(m.get("per_insertion") or [], 1):
        f = insertion_findings(pi, target, needle_length_mm, force_limit_n)
        worst = f[0]["severity"] if f else "good"
        change = next((x["change"] for x in f if x.get("change")), None)
        ins.append({"insertion": n, "worst": worst, "findings": f, "change": change})
    ins.sort(key=lambda x: (_RANK[x["worst"]], x["insertion"]))
    change = ins[0]["change"] if ins else None
    if not ins:
        headline = "the needle never went through the skin" if not summary.get("punctures") else "no insertion measured"
        change = "press on until the skin gives, then go on to the target depth" if not summary.get("punctures") else None
    else:
        bad = sum(1 for x in ins if x["worst"] in ("danger", "fault"))
        headline = (f"{len(ins)} insertion{'s' if len(ins) != 1 else ''}: "
                    + ("all as asked" if not bad else f"{bad} to correct"))
    return {"headline": headline, "insertions": ins, "change": change}


_MARK = {"danger": "!!", "fault": "! ", "note": "- ", "good": "ok"}


def debrief_lines(d: dict, width: int | None = None) -> list[str]:
    """The debrief as text lines wrapped to ``width`` (default: the terminal's, at least 40)."""
    if width is None:
        width = shutil.get_terminal_size((80, 24)).columns
    width = max(40, int(width))

    def wrap(text, first, rest):
        return textwrap.wrap(text, width=width, initial_indent=first, subsequent_indent=rest,
                             break_on_hyphens=False) or [first.rstrip()]

    out = wrap(f"Debrief: {d['headline']}", "", "  ")
    many = len(d["insertions"]) > 1
    for ins in d["insertions"]:
        pad = "  "
        if many:
            out.append(f"  insertion {ins['insertion']}:")
            pad = "    "
        for f in ins["findings"]:
            out += wrap(f["text"], f"{pad}{_MARK[f['severity']]} ", pad + "   ")
        if many and ins["change"]:
            out += wrap(f"next time: {ins['change']}", f"{pad}-> ", pad + "   ")
    if d["change"]:
        out += wrap(f"The one thing to change next time: {d['change']}", "  => ", "     ")
    return out


def debrief_markdown(d: dict, title: str = "Debrief") -> str:
    """The debrief as Markdown (``debrief.md`` in the report folder)."""
    out = [f"# {title}", "", d["headline"][0].upper() + d["headline"][1:] + ".", ""]
    if d["change"]:
        out += [f"**The one thing to change next time:** {d['change']}.", ""]
    words = {"danger": "**Danger**", "fault": "**Wrong**", "note": "Done", "good": "Right"}
    for ins in d["insertions"]:
        out += [f"## Insertion {ins['insertion']}", ""]
        for f in ins["findings"]:
            out.append(f"- {words[f['severity']]}: {f['text']}")
        if ins["change"]:
            out.append(f"- Next time: {ins['change']}")
        out.append("")
    return "\n".join(out)
