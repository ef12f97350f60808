"""The model's vocabulary, shared by the tissue model and the servo: where the tip is (place codes),
a layer's state at the insertion site, the force nets' buffers ("slots") and who owns them, the
post-puncture mechanics mode, and the sizes of the fixed-capacity memories (holes, tracks).
"""
from __future__ import annotations

from numba.extending import register_jitable

from ..base.config import LAYER_NAMES

PLACE_NAMES = ("outside", "skin", "fat", "muscle", "bone")  # where the tip is: PLACE_NAMES[DIAG.layer + 1]
OUTSIDE, SKIN, FAT, MUSCLE, BONE = range(-1, len(PLACE_NAMES) - 1)  # the place codes (DIAG.layer, tissue.locate)
N_LAYERS = len(LAYER_NAMES)
UNTOUCHED, PRESSING, PUNCTURED = 0, 1, 2  # a layer's state at the insertion site
STATE_NAMES = ("untouched", "pressing", "punctured")
N_SLOTS = 2  # net buffers per layer
FREE, SERVO_OWNS, VISUAL_OWNS = 0, 1, 2  # owner of a (layer, slot) net buffer
MAX_HOLES = 64
MAX_TRACKS = 32  # insertion tracks remembered (:mod:`.mechanics`'s track memory; the oldest is overwritten)
RICH, TABLE1 = 0, 1  # PARAMS.mechanics: cutting + Karnopp friction, or the paper's Table 1



@register_jitable
def net_index(k, s):
    """The index of layer ``k``'s slot ``s`` net in the per-net arrays (:data:`LAYOUT`'s blocks,
    ``SERVO.slot_q``, ``State.axes``, ``NeedleModel.x``...): slots of a layer are adjacent."""
    return N_SLOTS * k + s


@register_jitable
def net_layer(idx):
    """The layer of the net ``idx`` (:func:`net_index`)."""
    return idx // N_SLOTS


@register_jitable
def net_slot(idx):
    """The slot of the net ``idx`` (:func:`net_index`) within its layer."""
    return idx % N_SLOTS
