"""The studies made with the benchmark, apart from its own analysis: the paper's reproduction
and its claims, BDC's sensitivity, learned control against MPC, the generalisation matrix and
the mixed-traffic penetration study. Each builds on the harness (``benchmark``) and the
benchmark's analysis (``analysis``: stability, Pareto fronts, tables, figures); the commands
(``commands``) run them.
"""
