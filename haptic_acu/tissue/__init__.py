"""The tissue model, pure and compiled: the layered body between spherical-harmonic surfaces
(:mod:`.shf`, :mod:`.body`), the mass-spring force nets and their tabulated responses
(:mod:`.forcenet`, :mod:`.netresponse`), post-puncture mechanics (:mod:`.mechanics`,
:mod:`.postpuncture`), twirling (:mod:`.twirl`), springback (:mod:`.springback`), the vocabulary
of places and layer states (:mod:`.layers`), and the baseline tissue models of the paper's
comparison (:mod:`.baselines`; the mass-spring lattice, :mod:`.msm`; the finite elements, :mod:`.fem`; the
boundary elements, :mod:`.bem`).

May import: base.
"""
