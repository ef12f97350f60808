"""The blinded, counterbalanced user study of tissue models (the paper's section 4.2): the design
(:mod:`.design`: Williams squares, codes), the study folder (:mod:`.store`), a new study
(:mod:`.plan`), a trial's session (:mod:`.trial`), the ratings (:mod:`.ratings`), where it stands
(:mod:`.overview`), the statistics (:mod:`.stats`), the unblinded analysis (:mod:`.analyze`) and the
bundled synthetic study (:mod:`.example`). The command: :mod:`haptic_acu.cli.study`; docs/study.md.

May import: session, analysis, servo, tissue, base (it sits beside cohort; devices come from the cli).
"""
