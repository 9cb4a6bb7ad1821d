"""The evaluation protocols: which records and steps are scored, against which ground truth, and the
metric dicts — one module per kind. `services/cli/eval_tasks` turns their results into reports
(tables, plots, printed lines) and `services/bench` into the benchmark's JSON; neither scores anything.
"""
