"""What the compiled tick pressing the skin spends its time on: the bench's skin-press path (w = 10,
``bench/scenarios.py``) run inside one compiled loop per variant, each variant the step with fewer
phases (the full ``step_kernel``, then the phases one by one down to none), timed on the thread's
CPU clock (a shared host's other processes count less than on the wall clock). Per tick, in us,
the minimum and median over repeats; the differences between rows are the phases' costs.

    taskset -c 1 .venv/bin/python tools/tick_phases.py [REPEATS]
"""
import sys
import time

import numba as nb
import numpy as np

from haptic_acu.bench import scenarios
from haptic_acu.servo import step as st
from haptic_acu.servo import state as ss
from haptic_acu.servo.danger import danger_phase, danger_render
from haptic_acu.servo.samples import NCOL, write_sample
from haptic_acu.servo.state import TIMING, Ring, Timing
from haptic_acu.servo.tick import tick_table, unpack_tick

N_LAYERS = st.N_LAYERS
# (full step, radii, front gradient, contact, twirl, bone+danger+locate+clamp, render, sample row)
VARIANTS = {
    "step_kernel + sample row": (1, 0, 0, 0, 0, 0, 0, 1),
    "step_kernel": (1, 0, 0, 0, 0, 0, 0, 0),
    "phases, all": (0, 1, 1, 1, 1, 1, 1, 0),
    "  without render_local": (0, 1, 1, 1, 1, 1, 0, 0),
    "  and twirl": (0, 1, 1, 1, 0, 1, 0, 0),
    "  and bone/danger/locate/clamp": (0, 1, 1, 1, 0, 0, 0, 0),
    "  and the press (radii + gradient)": (0, 1, 1, 0, 0, 0, 0, 0),
    "  and the gradient (radii)": (0, 1, 0, 0, 0, 0, 0, 0),
    "  and the radii (input, clear)": (0, 0, 0, 0, 0, 0, 0, 0),
}


def variant(flags):
    full, radii, grad, contact, twirl, rest, render, sample = flags

    @nb.njit(nogil=True, _nrt=False)
    def ticks(P, V, R, table):
        sv, ring, _ = unpack_tick(table)
        inp, m, s, out = sv.inp, sv.model, sv.state, sv.out.diag
        for i in range(P.shape[0]):
            for c in range(3):
                inp.p[c] = P[i, c]
                inp.v[c] = V[i, c]
                inp.axis[c] = np.nan
            inp.roll[0] = R[i]
            if full:
                st.step_kernel(inp, m, s, out)
            else:
                d = out[0]
                ss.clear(out)
                ss.clear(s.work)
                d.puncture = -1.0
                d.layer = -1.0
                s.servo[0].tick += 1
                if not st.check_input(inp, s, d):
                    return
                st.track_entry(inp, s)
                st.front_layer(s)
                if radii:
                    st.tip_radii(m, s, s.work[0].front if grad else N_LAYERS)
                if contact and s.work[0].front < N_LAYERS:
                    st.front_contact(inp, m, s, d)
                if twirl:
                    st.twirl_phase(inp, m, s, d)
                if rest:
                    st.bone_wall(m, s, d)
                    danger_phase(inp, m, s, d)
                    st.locate(s, d)
                    st.clamp(m, s, d)
                if render:
                    st.render_local(m, s, d)
                    danger_render(s, d)
            if sample:
                write_sample(ring.buf, i % ring.buf.shape[0], 0.0, i, inp, s, out, 0.0)
    return ticks


def main() -> None:
    repeats = int(sys.argv[1]) if len(sys.argv) > 1 else 7
    sc = scenarios.press(5000, layer=0, w=10)
    model = scenarios.model_for(sc.cfg)
    model.warm_up()
    for p, v in zip(sc.pre_P, sc.pre_V):
        model.step(p, v)
    snap = model.copy_state()
    P, V, R = (np.ascontiguousarray(a) for a in (sc.P, sc.V, sc.R))
    ring = Ring(np.zeros((100, NCOL)), np.zeros(1, np.int64))
    timing = Timing(np.zeros(1), np.zeros(1, TIMING))
    table = tick_table(model.servo, ring, timing)
    kernels = {name: variant(f) for name, f in VARIANTS.items()}
    for k in kernels.values():  # compile
        model.restore_state(snap)
        k(P[:10], V[:10], R[:10], table)
    times = {name: [] for name in kernels}
    for _ in range(repeats):
        for name, k in kernels.items():
            model.restore_state(snap)
            t0 = time.thread_time_ns()
            k(P, V, R, table)
            times[name].append((time.thread_time_ns() - t0) / P.shape[0] / 1e3)
    print(f"{'compiled tick pressing the skin (us per tick)':46s} {'min':>6s} {'median':>7s}")
    for name, t in times.items():
        print(f"{name:46s} {min(t):6.3f} {np.median(t):7.3f}")


if __name__ == "__main__":
    main()
