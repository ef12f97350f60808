"""HD API emulator (a stand-in libHD.so) for testing devices.omni without a PHANTOM; see build.py."""
