"""What a session measured: punctures and per-place peaks from the sample rows (:mod:`.scan`),
per-insertion metrics (:mod:`.metrics`, streamed in bounded memory by :mod:`.insertion_stream`),
the lift-thrust and twirl technique (:mod:`.technique`), motion-skill metrics
(:mod:`.skill_metrics`), the paper's multi-index weighted score (:mod:`.scoring`) and its
files (:mod:`.score_files`), and sessions' metrics side by side (:mod:`.comparison`).

May import: servo, tissue, base.
"""
