"""``haptic-acu bench``: latency and throughput of the simulator, side by side with its peers.

Modules: :mod:`bench.scenarios` (configs and tip paths the servo step is timed on),
:mod:`bench.numpy_reference` (the same servo step written plainly with NumPy/SciPy, the peer a
Python developer would write first), :mod:`bench.measure` (timers, percentiles, machine info),
:mod:`bench.run` (every measurement, the table, the JSON) and :mod:`bench.cold_start_child`
(a replay run in a subprocess that reports when its first servo tick is done).

The bench reports numbers; it never fails on one (these machines are shared and noisy), only on a
crash.
"""

import haptic_acu  # noqa: F401,E402  (first: it makes BLAS single-threaded before NumPy loads)
