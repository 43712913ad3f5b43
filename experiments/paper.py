"""The CCR paper's published numbers (He, Zhao, Luo and Liu; ``docs/references.md``).

Tables I (dangerous-behaviour frequency) and II (success rate), every learner and
variant, as fractions; the paper's headline figures; and its columns' order. The
experiments print them beside ours; nothing in ccrjax is tuned to them except the
*plain* rows, which the scenarios' calibration on reference controllers aims at
(``experiments/calibrate.py``).
"""

from __future__ import annotations

PAPER_SCENARIOS = ("hidden_obstacle", "turbulence", "strong_wind")  # the paper's column order

_PAPER_ROWS = {
    "danger_frequency": {
        ("iddpg", "plain"): (40.86, 48.03, 32.63),
        ("iddpg", "pessimistic"): (22.80, 54.70, 19.97),
        ("iddpg", "ccr"): (8.41, 23.35, 19.24),
        ("maddpg", "plain"): (40.92, 52.35, 19.22),
        ("maddpg", "pessimistic"): (22.42, 57.86, 21.96),
        ("maddpg", "ccr"): (15.27, 34.97, 17.97),
        ("maac", "plain"): (69.34, 52.25, 12.15),
        ("maac", "pessimistic"): (42.87, 25.74, 25.73),
        ("maac", "ccr"): (28.89, 9.73, 16.25),
    },
    "success_rate": {
        ("iddpg", "plain"): (36.22, 97.48, 73.44),
        ("iddpg", "pessimistic"): (73.16, 56.18, 72.45),
        ("iddpg", "ccr"): (88.69, 70.34, 81.74),
        ("maddpg", "plain"): (33.80, 96.62, 70.40),
        ("maddpg", "pessimistic"): (73.53, 54.77, 79.75),
        ("maddpg", "ccr"): (75.79, 84.00, 77.15),
        ("maac", "plain"): (1.71, 97.19, 84.26),
        ("maac", "pessimistic"): (8.43, 78.41, 78.45),
        ("maac", "ccr"): (26.71, 67.50, 84.51),
    },
}
PAPER = {
    metric: {(scenario, algo, variant): values[k] / 100.0
             for (algo, variant), values in rows.items()
             for k, scenario in enumerate(PAPER_SCENARIOS)}
    for metric, rows in _PAPER_ROWS.items()
}
PAPER_HEADLINES = {
    "danger_reduction_vs_plain": 0.4224,
    "danger_reduction_vs_pessimistic": 0.3837,
    "success_change_vs_pessimistic": 0.3590,
    "success_change_vs_plain_turbulence": -0.2381,  # "an average of 23.81% lower"
    "training_danger_share_maddpg_hidden_obstacle": 0.2809,
}
# Behavioural analysis: MADDPG+CCR's robots keep "farther to the obstacle than those trained
# with MADDPG, by approximately 1.2x to 4.7x" (the average distance, robot by robot).
PAPER_OBSTACLE_DISTANCE_RATIO = (1.2, 4.7)
