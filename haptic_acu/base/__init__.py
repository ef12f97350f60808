"""Foundations every layer uses: the configuration (strict TOML into frozen dataclasses, ``--set``
overrides), user-facing errors, bundled data lookup, the kernel-cache guard, CSV number formatting,
progress lines, the session figures' layout and PNG (:mod:`.figlayout`), the garbage collector's
policy for a command's process (:mod:`.gcpolicy`) and the terminal prompt's line reader that a
Ctrl-C always ends (:mod:`.prompt`).

Imports nothing else of haptic_acu.
"""
