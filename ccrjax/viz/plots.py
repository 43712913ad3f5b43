"""Training curves: one panel per metric, mean over seeds with a 95% confidence band.

Used by the train command (``curves.png`` of a run) and by the experiments (one
curve per variant in the same panels). Matplotlib through ``Figure`` and the Agg
canvas, never ``pyplot``: no display needed, no global state touched.
"""

from __future__ import annotations

import dataclasses
import os
import textwrap
from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter

from ccrjax.run.folder import METRIC_RANGES, METRIC_TITLES, replacing
from ccrjax.run.stats import mean_ci_along
from ccrjax.run.sweep_grid import REFERENCE_NAME
from ccrjax.viz.render import characters_per_line

PALETTE = ("#1f6fd1", "#d1495b", "#2a9d8f", "#e9a03b", "#6a4c93", "#8c8c8c")
CURVE_METRICS = (
    "success_rate", "target_distance", "danger_frequency", "return", "hazard_distance",
    "cumulative_danger_steps",
)


def short_number(value: float, _position: int | None = None) -> str:
    """Axis labels that never run together: 100k, 1.5M, 250."""
    magnitude = abs(value)
    for divisor, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if magnitude >= divisor:
            return f"{value / divisor:g}{suffix}"
    return f"{value:g}"


def save_figure(fig: Figure, path: str | os.PathLike[str], dpi: int | None = None) -> None:
    """Writes ``fig`` to ``path`` whole (:func:`ccrjax.run.folder.replacing`)."""
    with replacing(path) as temporary:
        fig.savefig(temporary, dpi=dpi or fig.dpi)


class Curves:
    """The runs to draw: ``label -> (env_steps [P], {metric: values [seeds, P]})``, each
    in its own colour (given, or the palette's next)."""

    def __init__(self) -> None:
        self.series: dict[str, tuple[np.ndarray, dict[str, np.ndarray]]] = {}
        self.colours: dict[str, str] = {}

    def add(self, label: str, env_steps: Sequence[int], values: dict[str, np.ndarray],
            colour: str | None = None) -> None:
        steps = np.asarray(env_steps)
        for name, array in values.items():
            array = np.asarray(array, dtype=np.float64)
            if array.ndim != 2 or array.shape[1] != steps.size:
                raise ValueError(
                    f"curve {label!r}: {name} must be [seeds, {steps.size}], got {array.shape}"
                )
        self.series[label] = (steps, {k: np.asarray(v, np.float64) for k, v in values.items()})
        if colour is not None:
            self.colours[label] = colour


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
                lines: dict[str, tuple[float, str]] | None = None, dpi: int = 120) -> None:
    """One panel per metric: each run's mean over seeds, its 95% band, its seeds faint;
    ``lines`` a dashed horizontal line and its label on some panels (a cost limit)."""
    columns = 2 if len(metrics) == 4 else min(3, len(metrics))  # no empty panel for 4
    rows = -(-len(metrics) // columns)
    fig = Figure(figsize=(4.2 * columns, 3.0 * rows + (0.4 if title else 0.0)), dpi=dpi)
    FigureCanvasAgg(fig)
    for index, metric in enumerate(metrics):
        ax = fig.add_subplot(rows, columns, index + 1)
        for colour_index, (label, (steps, values)) in enumerate(curves.series.items()):
            if metric not in values:
                continue
            colour = curves.colours.get(label, PALETTE[colour_index % len(PALETTE)])
            per_seed = values[metric]
            bounds = METRIC_RANGES.get(metric, (-np.inf, np.inf))
            mean, low, high = mean_ci_along(per_seed, axis=0, bounds=bounds)
            n = per_seed.shape[0]
            ax.plot(steps, mean, color=colour, linewidth=1.8,
                    label=f"{label} (n={n} seed{'s' if n > 1 else ''})" if index == 0 else None)
            if n > 1:
                ax.fill_between(steps, low, high, color=colour, alpha=0.2, linewidth=0)
                for seed_values in per_seed:
                    ax.plot(steps, seed_values, color=colour, linewidth=0.6, alpha=0.3)
        if lines and metric in lines:
            value, text = lines[metric]
            ax.axhline(value, color="black", linestyle="--", linewidth=1.0)
            ax.annotate(text, (0.99, value), xycoords=("axes fraction", "data"), ha="right",
                        va="bottom", fontsize=7)
        ax.set_title(METRIC_TITLES.get(metric, metric), fontsize=10)
        ax.set_xlabel("environment steps per seed", fontsize=8)
        ax.xaxis.set_major_formatter(FuncFormatter(short_number))
        ax.yaxis.set_major_formatter(FuncFormatter(short_number))  # counts reach 100k and more
        ax.tick_params(labelsize=8)
        ax.grid(alpha=0.3)
        if metric in ("success_rate", "danger_frequency"):
            ax.set_ylim(-0.02, 1.02)
    handles, labels = fig.axes[0].get_legend_handles_labels()
    if title:
        fig.suptitle(title, fontsize=11)
    if handles:  # below the panels, never over a curve
        # The common words once, as the legend's title: the labels stay short enough to
        # sit side by side on any figure width.
        several = any(values[m].shape[0] > 1 for _, values in curves.series.values()
                      for m in metrics if m in values)
        caption = ("mean (bold), 95% CI over seeds (band, clipped to the metric's range), each "
                   "seed (faint)" if several else "one seed: no interval")
        fig.legend(handles, labels, loc="lower center", ncol=len(handles), fontsize=9,
                   frameon=False, title=caption, title_fontsize=9)
        fig.tight_layout(rect=(0, 0.15 / rows, 1, 1))
    else:
        fig.tight_layout()
    save_figure(fig, path, dpi)


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
        mean, low, high = mean_ci_along(values, axis=0, bounds=(0.0, np.inf))
        positions = np.arange(1, values.shape[1] + 1) + (index - (len(series) - 1) / 2) * width
        ax.bar(positions, mean, width=width, yerr=np.stack([mean - low, high - mean]), capsize=3,
               color=colours[index % len(colours)], label=f"{label} (n={values.shape[0]} seeds)")
    ax.set_xticks(np.arange(1, values.shape[1] + 1))
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path)


def draw_obstacle_distances(plain: np.ndarray, ccr: np.ndarray,
                            path: str | os.PathLike[str], note: str = "") -> None:
    """The paper's behavioural analysis as a figure: per robot in order of arrival at the
    hidden obstacle, the average distance to its centre (``[seeds, robots]`` each), plain
    MADDPG against MADDPG+CCR, with 95% intervals over seeds; ``note`` a line above the title."""
    draw_rank_bars(
        {"MADDPG": plain, "MADDPG+CCR": ccr}, path,
        xlabel="robot, in order of arrival at the obstacle",
        ylabel="average distance to the obstacle centre",
        title=(f"{note.strip()}\n" if note else "")
        + "hidden obstacle: every robot's average distance to the obstacle's centre over the "
        "episode\n(successful or not, as in the paper's figure; mean, 95% CI over seeds)",
    )


PARAMETER_SYMBOLS = {"lam": "λ", "penalty": "penalty"}
PANEL_WIDTH = 4.0  # inches, of one search panel


def _interval(stats: dict) -> tuple[float, float]:
    """The distances from the mean to the (clipped) ends of a ``mean_ci`` summary."""
    if stats.get("ci_low") is None:
        return 0.0, 0.0
    return stats["mean"] - stats["ci_low"], stats["ci_high"] - stats["mean"]


@dataclasses.dataclass(frozen=True)
class SearchChoice:
    """What a search's selection rule decided, drawn on its panel: the success rate below
    which a value is not eligible (``threshold``), the value chosen, and how the choice
    is named (``label``: "chosen", or "provisional choice" before every pair exists)."""

    value: float
    threshold: float
    label: str = "chosen"


def draw_search_tradeoff(panels: dict[str, Sequence[dict]], parameter: str,
                         path: str | os.PathLike[str], *,
                         choices: dict[str, SearchChoice] | None = None,
                         dpi: int = 120) -> None:
    """Danger frequency against success rate, one point per searched value with its 95%
    intervals (clipped to [0, 1]), one panel per title in ``panels`` (rows of
    :func:`ccrjax.run.sweep_grid.search_rows`). Values are told apart by colour, named once in the
    legend below the panels, so no label covers another. A panel named in ``choices``
    also shows the rule's decision: the values left of the dashed line (success too far
    below the reference's) are shaded as not eligible, and the chosen value is ringed."""
    choices = choices or {}
    titles = list(panels)
    columns = min(3, len(titles))
    rows = -(-len(titles) // columns)
    values = sorted({row["value"] for rows_ in panels.values() for row in rows_})
    legend_columns = min(len(values), 2 * columns + 1)
    legend_rows = -(-len(values) // legend_columns)
    legend_height = 0.25 + 0.2 * legend_rows  # inches: the legend's title and rows
    fig = Figure(figsize=(PANEL_WIDTH * columns + 0.6, 3.4 * rows + legend_height), dpi=dpi)
    FigureCanvasAgg(fig)
    colours = {value: _value_colour(index, len(values)) for index, value in enumerate(values)}
    symbol = PARAMETER_SYMBOLS.get(parameter, parameter)
    for index, title in enumerate(titles):
        ax = fig.add_subplot(rows, columns, index + 1)
        for row in panels[title]:
            success, danger = row["success_rate"], row["danger_frequency"]
            label = f"{symbol} = {row['value']:g}" + (
                f" ({REFERENCE_NAME.get(parameter, 'reference')})" if row["value"] == 0 else "")
            ax.errorbar(success["mean"], danger["mean"],
                        xerr=np.array(_interval(success))[:, None],
                        yerr=np.array(_interval(danger))[:, None],
                        marker="s" if row["value"] == 0 else "o", capsize=3, linewidth=1,
                        color=colours[row["value"]], label=label if index == 0 else None)
        if title in choices:
            _draw_choice(ax, choices[title], panels[title])
        ax.set_xlim(-0.03, 1.03)
        ax.set_ylim(bottom=-0.01)
        ax.set_title(textwrap.fill(title, characters_per_line(PANEL_WIDTH, 9)), fontsize=9)
        ax.set_xlabel("success rate (higher is better)", fontsize=8)
        ax.set_ylabel("danger frequency (lower is better)", fontsize=8)
        ax.tick_params(labelsize=8)
        ax.grid(alpha=0.3)
    entries: dict[str, Any] = {}
    for ax in fig.axes:  # the values (named on the first panel) and any choice's marks
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            entries.setdefault(label, handle)
    marks = {NOT_ELIGIBLE, *(choice.label for choice in choices.values())}
    labels = sorted(entries, key=lambda label: label in marks)  # the values first
    handles = [entries[label] for label in labels]
    legend = fig.legend(handles, labels, loc="lower center", ncol=legend_columns, fontsize=8,
                        frameon=False, title="mean and 95% CI over seeds", title_fontsize=8)
    # Long labels (penalty = 0.03 ...) can make the legend wider than the panels: widen the
    # figure to hold it rather than cut its first and last columns off.
    legend_width = legend.get_window_extent(fig.canvas.get_renderer()).width / fig.dpi
    fig.set_figwidth(max(fig.get_figwidth(), legend_width + 0.3))
    fig.tight_layout(rect=(0, legend_height / (3.4 * rows + legend_height), 1, 1))
    save_figure(fig, path)


NOT_ELIGIBLE = "not eligible (low success)"


def _draw_choice(ax: Any, choice: SearchChoice, rows: Sequence[dict]) -> None:
    """The selection rule's threshold and the chosen value on one tradeoff panel."""
    ax.axvspan(-0.03, choice.threshold, color="0.5", alpha=0.12, linewidth=0,
               label=NOT_ELIGIBLE)
    ax.axvline(choice.threshold, color="0.35", linestyle="--", linewidth=0.9)
    for row in rows:
        if row["value"] == choice.value:
            ax.plot(row["success_rate"]["mean"], row["danger_frequency"]["mean"],
                    marker="o", markersize=15, markerfacecolor="none",
                    markeredgecolor="black", markeredgewidth=1.2, linestyle="none",
                    label=choice.label)


def _value_colour(index: int, count: int) -> tuple[float, float, float, float]:

    return colormaps["viridis"](index / max(1, count - 1) * 0.9)


VARIANT_COLOURS = {"plain": "#8c8c8c", "pessimistic": "#1f6fd1", "ccr": "#ff5fa2"}


def draw_progress_matched(panels: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]],
                          path: str | os.PathLike[str], *, title: str, dpi: int = 120) -> None:
    """Danger against return along training: one panel per title in ``panels``, one line
    per variant through its evaluations (``(returns, danger)``, each ``[seeds, points]``):
    every seed's path faint, the mean over seeds bold, and at every evaluation a cross of
    the 95% intervals over seeds of danger (vertical, clipped to [0, 1]) and of return
    (horizontal, clipped to at most 0): bars, not a band, since the mean path may turn back
    along the return axis; the first evaluation is marked by a square, the last by a disc.
    Reading across at equal return compares the variants at the same stage of learning: a
    variant that is safer only because it has progressed less sits to the left on the
    baseline's own curve."""
    columns = len(panels)
    fig = Figure(figsize=(4.4 * columns, 4.0), dpi=dpi)
    FigureCanvasAgg(fig)
    for index, (panel, series) in enumerate(panels.items()):
        ax = fig.add_subplot(1, columns, index + 1)
        for number, (variant, (returns, danger)) in enumerate(series.items()):
            colour = VARIANT_COLOURS.get(variant, PALETTE[number % len(PALETTE)])
            for seed_returns, seed_danger in zip(returns, danger, strict=True):
                ax.plot(seed_returns, seed_danger, color=colour, linewidth=0.5, alpha=0.25)
            x, x_low, x_high = mean_ci_along(returns, axis=0, bounds=METRIC_RANGES["return"])
            y, y_low, y_high = mean_ci_along(danger, axis=0,
                                             bounds=METRIC_RANGES["danger_frequency"])
            ax.vlines(x, y_low, y_high, color=colour, alpha=0.35, linewidth=0.9)
            ax.hlines(y, x_low, x_high, color=colour, alpha=0.35, linewidth=0.9)
            ax.plot(x, y, color=colour, linewidth=1.6,
                    label=f"{variant} (n={returns.shape[0]} seeds)" if index == 0 else None)
            ax.plot(x[:1], y[:1], marker="s", color=colour, markersize=6)
            ax.plot(x[-1:], y[-1:], marker="o", color=colour, markersize=7)
        ax.set_title(panel, fontsize=10)
        ax.set_xlabel("evaluated return (higher = further along)", fontsize=8)
        ax.set_ylabel("dangerous-behaviour frequency", fontsize=8)
        ax.set_ylim(bottom=-0.01)
        ax.tick_params(labelsize=8)
        ax.grid(alpha=0.3)
    handles, labels = fig.axes[0].get_legend_handles_labels()
    fig.suptitle(title, fontsize=11)
    fig.legend(handles, labels, loc="lower center", ncol=len(handles), fontsize=8,
               frameon=False, title="mean over seeds (bold), each seed (faint), bars: 95% CI "
               "over seeds of danger and of return; ■ first, ● last evaluation",
               title_fontsize=8)
    fig.tight_layout(rect=(0, 0.12, 1, 1))
    save_figure(fig, path)
