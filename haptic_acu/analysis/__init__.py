"""What a session measured: punctures and per-place peaks from the sample rows (:mod:`.scan`),
per-insertion metrics (:mod:`.metrics`, streamed in bounded memory by :mod:`.insertion_stream`),
the lift-thrust and twirl technique (:mod:`.technique`), motion-skill metrics
(:mod:`.skill_metrics`) and the paper's multi-index weighted score (:mod:`.scoring`).

May import: servo, tissue, base.
"""
