"""What runs a session and writes it: the engine and its drivers (:mod:`.engine`), headless replay
(:mod:`.replay`), trajectories (:mod:`.trajectory`), the outputs, each a :class:`.sink.Sink`
(recorder, report, rerun logging, status line, path metrics), the sink process and the viewer;
sessions compared (:mod:`.compare`), a batch's tables (:mod:`.batch`) and a live session's report
(:mod:`.live`).

May import: analysis, servo, tissue, base, and haptic_acu.devices.
"""
