"""The device layer: one small interface (:class:`devices.base.Device`) and its implementations.

* :mod:`devices.scripted` - plays a trajectory file (headless replay, CI).
* :mod:`devices.keyboard` - keys in a terminal move the needle (works over plain SSH).
* :mod:`devices.omni`     - the PHANTOM OMNI through ``pyOpenHaptics`` (imported lazily: it loads
  ``libHD.so`` at import time).
"""
from .base import Device, DeviceInfo, DeviceState, Workspace

__all__ = ["Device", "DeviceInfo", "DeviceState", "Workspace"]
