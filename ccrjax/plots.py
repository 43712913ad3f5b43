"""Training curves: one panel per metric, mean over seeds with a 95% confidence band.

Used by the train command (``curves.png`` of a run) and by the experiments (one
curve per variant in the same panels). Matplotlib through ``Figure`` and the Agg
canvas, never ``pyplot``: no display needed, no global state touched.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ccrjax.run_folder import METRIC_TITLES
from ccrjax.stats import mean_ci_along

PALETTE = ("#1f6fd1", "#d1495b", "#2a9d8f", "#e9a03b", "#6a4c93", "#8c8c8c")
CURVE_METRICS = (
    "success_rate", "target_distance", "danger_frequency", "return", "hazard_distance",
    "cumulative_danger_steps",
)


class Curves:
    """The runs to draw: ``label -> (env_steps [P], {metric: values [seeds, P]})``."""

    def __init__(self) -> None:
        self.series: dict[str, tuple[np.ndarray, dict[str, np.ndarray]]] = {}

    def add(self, label: str, env_steps: Sequence[int], values: dict[str, np.ndarray]) -> None:
        steps = np.asarray(env_steps)
        for name, array in values.items():
            array = np.asarray(array, dtype=np.float64)
            if array.ndim != 2 or array.shape[1] != steps.size:
                raise ValueError(
                    f"curve {label!r}: {name} must be [seeds, {steps.size}], got {array.shape}"
                )
        self.series[label] = (steps, {k: np.asarray(v, np.float64) for k, v in values.items()})


def curves_from_rows(rows: Sequence[dict], metrics: Sequence[str] = CURVE_METRICS):
    """``(env_steps [P], {metric: [seeds, P]})`` from ``metrics.csv`` rows (one per seed and
    point); the points every seed has."""
    seeds = sorted({row["seed"] for row in rows})
    by_seed = {seed: sorted((r for r in rows if r["seed"] == seed), key=lambda r: r["env_steps"])
               for seed in seeds}
    length = min(len(v) for v in by_seed.values())
    steps = np.array([r["env_steps"] for r in by_seed[seeds[0]][:length]])
    values = {m: np.array([[r[m] for r in by_seed[s][:length]] for s in seeds]) for m in metrics}
    return steps, values


def draw_curves(curves: Curves, path: str | os.PathLike[str], *,
                metrics: Sequence[str] = CURVE_METRICS, title: str | None = None,
                dpi: int = 120) -> None:
    """One panel per metric: each run's mean over seeds, its 95% band, its seeds faint."""
    columns = min(3, len(metrics))
    rows = -(-len(metrics) // columns)
    fig = Figure(figsize=(4.2 * columns, 3.0 * rows + (0.4 if title else 0.0)), dpi=dpi)
    FigureCanvasAgg(fig)
    for index, metric in enumerate(metrics):
        ax = fig.add_subplot(rows, columns, index + 1)
        for colour_index, (label, (steps, values)) in enumerate(curves.series.items()):
            if metric not in values:
                continue
            colour = PALETTE[colour_index % len(PALETTE)]
            per_seed = values[metric]
            mean, half = mean_ci_along(per_seed, axis=0)
            n = per_seed.shape[0]
            ax.plot(steps, mean, color=colour, linewidth=1.8,
                    label=f"{label} (n={n} seeds)" if index == 0 else None)
            if n > 1:
                ax.fill_between(steps, mean - half, mean + half, color=colour, alpha=0.2,
                                linewidth=0)
                for seed_values in per_seed:
                    ax.plot(steps, seed_values, color=colour, linewidth=0.6, alpha=0.3)
        ax.set_title(METRIC_TITLES.get(metric, metric), fontsize=10)
        ax.set_xlabel("environment steps per seed", fontsize=8)
        ax.tick_params(labelsize=8)
        ax.grid(alpha=0.3)
        if metric in ("success_rate", "danger_frequency"):
            ax.set_ylim(-0.02, 1.02)
    handles, labels = fig.axes[0].get_legend_handles_labels()
    if title:
        fig.suptitle(title, fontsize=11)
    if handles:  # below the panels, never over a curve
        fig.legend(handles, [f"{label}: mean, 95% CI over seeds" for label in labels],
                   loc="lower center", ncol=len(handles), fontsize=9, frameon=False)
        fig.tight_layout(rect=(0, 0.09 / rows, 1, 1))
    else:
        fig.tight_layout()
    fig.savefig(os.fspath(path), dpi=dpi)


def draw_rank_bars(series: dict[str, np.ndarray], path: str | os.PathLike[str], *, xlabel: str,
                   ylabel: str, title: str, colours: Sequence[str] = ("#8c8c8c", "#ff5fa2"),
                   dpi: int = 130) -> None:
    """Grouped bars: for each position ``k`` (x) a bar per series, the mean over seeds of
    ``values[:, k]`` (``series[label]`` is ``[seeds, K]``) with its 95% interval."""
    fig = Figure(figsize=(6.4, 3.6), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    width = 0.8 / max(1, len(series))
    for index, (label, values) in enumerate(series.items()):
        values = np.asarray(values, np.float64)
        mean, half = mean_ci_along(values, axis=0)
        positions = np.arange(1, values.shape[1] + 1) + (index - (len(series) - 1) / 2) * width
        ax.bar(positions, mean, width=width, yerr=half, capsize=3,
               color=colours[index % len(colours)], label=f"{label} (n={values.shape[0]} seeds)")
    ax.set_xticks(np.arange(1, values.shape[1] + 1))
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    temporary = os.fspath(path) + ".tmp.png"
    fig.savefig(temporary)
    os.replace(temporary, path)


def draw_obstacle_distances(plain: np.ndarray, ccr: np.ndarray,
                            path: str | os.PathLike[str]) -> None:
    """The paper's behavioural analysis as a figure: per robot in order of arrival at the
    hidden obstacle, the average distance to its centre (``[seeds, robots]`` each), plain
    MADDPG against MADDPG+CCR, with 95% intervals over seeds."""
    draw_rank_bars(
        {"MADDPG": plain, "MADDPG+CCR": ccr}, path,
        xlabel="robot, in order of arrival at the obstacle",
        ylabel="average distance to the obstacle centre",
        title="hidden obstacle: distance kept from the obstacle (mean, 95% CI over seeds)",
    )
