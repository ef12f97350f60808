"""Foundations every layer uses: the configuration (strict TOML into frozen dataclasses, ``--set``
overrides), user-facing errors, bundled data lookup, the kernel-cache guard, CSV number formatting,
progress lines and the garbage collector's policy for a command's process.

Imports nothing else of haptic_acu.
"""
