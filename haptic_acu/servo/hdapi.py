"""The OpenHaptics HD API's constants that haptic-acu uses (the values of the HD API headers, as in
``pyOpenHaptics.hd_define``), declared once for the OMNI device (``devices/omni.py``) and its compiled
callback (:mod:`haptic_acu.servo.omniloop`). Plain integers: importing this loads no library."""

HD_SUCCESS = 0x0000
HD_INVALID_ENUM = 0x0100
HD_BAD_HANDLE = 0x0104
HD_CURRENT_BUTTONS = 0x2000
HD_CURRENT_VELOCITY = 0x2051
HD_CURRENT_TRANSFORM = 0x2052
HD_CURRENT_GIMBAL_ANGLES = 0x2150  # the third is the stylus roll (rad, wrapping at +-pi)
HD_DEVICE_MODEL_TYPE = 0x2501
HD_NOMINAL_MAX_STIFFNESS = 0x2602
HD_NOMINAL_MAX_FORCE = 0x2603
HD_NOMINAL_MAX_CONTINUOUS_FORCE = 0x2604
HD_NOMINAL_MAX_DAMPING = 0x2609
HD_CURRENT_FORCE = 0x2700
HD_FORCE_OUTPUT = 0x4000
HD_INVALID_HANDLE = 0xFFFFFFFF
HD_CALLBACK_DONE = 0
HD_CALLBACK_CONTINUE = 1
HD_MAX_SCHEDULER_PRIORITY = 0xFFFF
