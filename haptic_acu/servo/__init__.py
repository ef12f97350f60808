"""What runs at 1 kHz: the servo's named state (:mod:`.state`), one step of named phases
(:mod:`.step`), the one tick every driver calls (:mod:`.tick`), the compiled loops (:mod:`.rtloop`,
and :mod:`.omniloop` on the OMNI's scheduler), the rendering layer between the model and the device
(:mod:`.rendering`, :mod:`.clamp`), the stylus and device models used to check it (:mod:`.stylus`,
:mod:`.devicemodel`) and the lock-free sample ring (:mod:`.samples`).

May import: tissue, base.
"""
