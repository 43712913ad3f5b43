"""What is about the paper: its published numbers (:mod:`experiments.paper`), the
preregistered protocol's numbers and selection rule (:mod:`experiments.protocol`,
:mod:`experiments.selection`), the searches, tables, budgets and calibrations that apply it,
and their committed results (``experiments/results/``). Each script is a command:
``python -m experiments.tables --help`` (or ``python experiments/tables.py --help``)."""
