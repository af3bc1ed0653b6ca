"""``mfvs experiment NAME``: the seed papers' experiments, each a comparison of runs from one start, run through
the real services in lockstep (so every run, and every rerun, is the same to the bit), reported beside the paper.

================  ========================================================================================
table3            Sensors 2022 Table 3: the four laws with the paper's gains; iterations to ‖e‖ < 5e-5, beside
                  446/189/114/79
part-a            Sensors 2022 Part A: the end-effector twist sent as if it were mixed (the conventional mistake)
                  diverges; the mixed law converges
part-b            Sensors 2022 Part B: an outstretched start near the workspace's boundary: joint law against mixed
part-c            Sensors 2022 Part C: a start whose straight-line motion would pass through the base's zone
part-d            Sensors 2022 Part D: the mixed twist realised in joint space through Jm⁺ (eq. 26)
constraints       Muñoz 2018 section 9.1-like: one task in which every constraint type binds (field of view,
                  occlusion, joint range, joint speed, a forbidden sphere), with exact gradients and with 30 %
                  gradient error (eq. 49): max φ against the chattering band T_s·u⁺ (eq. 43), time active
tracking-region   Nelson 1995: a target moving at 10 cm/s, tracked on two translational axes without the
                  manipulability term and on four axes with it: distance tracked before failure, its cause
torque-control    JACO thesis chapter 5: five torque controllers over the 500 Hz low-level API, in realtime, each
                  a process of its own (:mod:`services.experiments.torque_control`; not a servo comparison)
================  ========================================================================================

Each experiment has a default start (``examples/scenarios/``); ``--scenario`` runs the same comparison from a
user's start and goal. Sensors 2022's experiments replace the scenario's law, gains and law options by each run's own;
``constraints`` keeps the scenario's constraints (they are the case) and sets only the gradient error, and
``tracking-region`` keeps its tuning and sets only the axes and, for the baseline, S = 0. The result is one JSON
shape for every experiment (:func:`run_experiment`); with an output directory each run's log and figures go in a
folder of their own, and the comparison's figures and a ``report.md`` beside them.

Here: each paper's experiments in a module named after what it reproduces (:mod:`.mixed_frame`, :mod:`.constraints`,
:mod:`.tracking_region`, :mod:`.torque_control`), what an experiment and its rows are (:mod:`.spec`), the one
registry the command line asks (:mod:`.registry`), random starts (:mod:`.starts`, :mod:`.random_starts`), runs side
by side (:mod:`.pool`), the report (:mod:`.report`) and the figures (:mod:`.figures`).
"""
