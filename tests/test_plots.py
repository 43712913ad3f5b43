"""The figures (:mod:`ccrjax.viz.plots`) at a small size: they render, their axes read, and
their intervals stay within each metric's range."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.axes import Axes
from PIL import Image

from ccrjax.viz import plots


@pytest.mark.parametrize("value, text", [(250, "250"), (100_000, "100k"), (1_500_000, "1.5M"),
                                         (3e9, "3G"), (0, "0"), (-20_000, "-20k")])
def test_axis_numbers_are_short(value, text):
    assert plots.short_number(value) == text


def is_picture(path) -> bool:
    with Image.open(path) as image:
        return image.format == "PNG" and np.unique(np.asarray(image.convert("L"))).size > 10


def test_curves_bands_stay_in_range(tmp_path, monkeypatch):
    """Success rates at 1 with spread: the drawn band never passes 1 (nor below 0); a
    series given a colour is drawn in it, the others in the palette's."""
    bands, colours = [], []
    original = Axes.fill_between

    def spy(self, x, low, high, **kwargs):
        bands.append((np.asarray(low), np.asarray(high)))
        colours.append(kwargs.get("color"))
        return original(self, x, low, high, **kwargs)

    monkeypatch.setattr(Axes, "fill_between", spy)
    curves = plots.Curves()
    success = np.array([[0.0, 0.9, 1.0], [0.1, 1.0, 1.0], [0.0, 1.0, 0.98]])
    curves.add("plain", [0, 100_000, 200_000], {"success_rate": success,
                                                "danger_frequency": 1 - success})
    curves.add("ccr", [0, 100_000, 200_000], {"success_rate": success / 2,
                                              "danger_frequency": success / 2},
               colour=plots.VARIANT_COLOURS["ccr"])
    path = tmp_path / "curves.png"
    plots.draw_curves(curves, path, metrics=("success_rate", "danger_frequency"))
    assert is_picture(path)
    assert len(bands) == 4
    for low, high in bands:
        assert low.min() >= 0.0 and high.max() <= 1.0
    assert colours == [plots.PALETTE[0], plots.VARIANT_COLOURS["ccr"]] * 2


def test_search_and_progress_figures_render(tmp_path):
    def stats(mean):
        return {"mean": mean, "ci_low": max(0.0, mean - 0.1), "ci_high": min(1.0, mean + 0.1)}

    rows = [{"value": v, "success_rate": stats(s), "danger_frequency": stats(d)}
            for v, s, d in ((0.0, 0.9, 0.3), (1.0, 0.85, 0.2), (10.0, 0.5, 0.05))]
    path = tmp_path / "tradeoff.png"
    plots.draw_search_tradeoff({"a": rows, "b": rows}, "lam", path)
    assert is_picture(path)


def test_a_long_search_panel_title_wraps_inside_the_figure(tmp_path, monkeypatch):
    """The quick mode's title (its warning first) on a figure of one panel, and the
    seven values with long labels and the rule's marks in the legend: all inside the figure."""
    figures = []
    save = plots.save_figure

    def keep(fig, path, dpi=None):
        figures.append(fig)
        save(fig, path, dpi)

    monkeypatch.setattr(plots, "save_figure", keep)
    rows = [{"value": v, "success_rate": {"mean": s}, "danger_frequency": {"mean": d}}
            for v, s, d in ((0.0, 0.9, 0.3), (0.0003, 0.9, 0.3), (0.003, 0.9, 0.3),
                            (0.03, 0.9, 0.3), (1.0, 0.87, 0.2), (3.0, 0.8, 0.1),
                            (10.0, 0.5, 0.05))]
    choice = plots.SearchChoice(value=1.0, threshold=0.85, label="provisional choice")
    title = ("[quick mode: measures nothing] pessimistic: averaged over 9 scenario x learner "
             "pair(s)")
    plots.draw_search_tradeoff({title: rows}, "penalty", tmp_path / "tradeoff.png",
                               choices={title: choice})
    (fig,) = figures
    renderer = fig.canvas.get_renderer()
    (ax,) = fig.axes
    box = ax.title.get_window_extent(renderer)
    assert ax.title.get_text().replace("\n", " ") == title
    assert box.x0 >= 0 and box.x1 <= fig.bbox.x1 and box.y1 <= fig.bbox.y1, (box, fig.bbox)
    # The legend below the panel fits as well, however long the values' labels.
    (legend,) = fig.legends
    box = legend.get_window_extent(renderer)
    assert box.x0 >= 0 and box.x1 <= fig.bbox.x1 and box.y0 >= 0, (box, fig.bbox)


def test_the_search_figure_shows_the_rules_decision(tmp_path, monkeypatch):
    """The panel given a choice shades what is not eligible, left of the threshold, and
    rings the chosen value's point; the other panel shows neither; the legend names both."""
    spans, rings, legends = [], [], []
    axvspan, plot, legend = Axes.axvspan, Axes.plot, plots.Figure.legend

    def spy_axvspan(self, low, high, **kwargs):
        spans.append((low, high))
        return axvspan(self, low, high, **kwargs)

    def spy_plot(self, *args, **kwargs):
        if kwargs.get("markerfacecolor") == "none":
            rings.append(args)
        return plot(self, *args, **kwargs)

    def spy_legend(self, handles, labels, **kwargs):
        legends.extend(labels)
        return legend(self, handles, labels, **kwargs)

    monkeypatch.setattr(Axes, "axvspan", spy_axvspan)
    monkeypatch.setattr(Axes, "plot", spy_plot)
    monkeypatch.setattr(plots.Figure, "legend", spy_legend)
    rows = [{"value": v, "success_rate": {"mean": s}, "danger_frequency": {"mean": d}}
            for v, s, d in ((0.0, 0.9, 0.3), (1.0, 0.87, 0.2), (10.0, 0.5, 0.05))]
    choice = plots.SearchChoice(value=1.0, threshold=0.85, label="provisional choice")
    path = tmp_path / "tradeoff.png"
    plots.draw_search_tradeoff({"all": rows, "one": rows}, "lam", path, choices={"all": choice})
    assert is_picture(path)
    assert [high for _, high in spans] == [0.85]  # on one panel only
    assert rings == [(0.87, 0.2)]
    assert "provisional choice" in legends and plots.NOT_ELIGIBLE in legends
    assert legends.count("λ = 1") == 1


def test_progress_figure_draws_every_seed_and_intervals_within_range(tmp_path, monkeypatch):
    """Danger near 0 with spread: its interval bars never go below 0, the return's never
    above 0; every seed of every variant has its own faint path."""
    bars, spans, lines = [], [], []
    vlines, hlines, plot = Axes.vlines, Axes.hlines, Axes.plot

    def spy_vlines(self, x, low, high, **kwargs):
        bars.append((np.asarray(low), np.asarray(high)))
        return vlines(self, x, low, high, **kwargs)

    def spy_hlines(self, y, low, high, **kwargs):
        spans.append((np.asarray(low), np.asarray(high)))
        return hlines(self, y, low, high, **kwargs)

    def spy_plot(self, *args, **kwargs):
        lines.append(kwargs.get("alpha"))
        return plot(self, *args, **kwargs)

    monkeypatch.setattr(Axes, "vlines", spy_vlines)
    monkeypatch.setattr(Axes, "hlines", spy_hlines)
    monkeypatch.setattr(Axes, "plot", spy_plot)
    rng = np.random.default_rng(0)
    returns = np.minimum(-6 + 2 * np.cumsum(rng.random((3, 6)), axis=1), -0.01)  # near 0
    danger = np.array([[0.0, 0.2, 0.0, 0.0, 0.3, 0.0]] * 2 + [[0.3, 0.0, 0.2, 0.0, 0.0, 0.1]])
    path = tmp_path / "progress.png"
    plots.draw_progress_matched({"MADDPG": {"plain": (returns, danger),
                                            "ccr": (returns, danger / 2)}}, path, title="t")
    assert is_picture(path)
    assert len(bars) == len(spans) == 2
    for low, high in bars:
        assert low.min() >= 0.0 and high.max() <= 1.0 and (low <= high).all()
        assert low.min() == 0.0  # clipped: the spread would take it below 0
    for low, high in spans:
        assert high.max() == 0.0 and (low <= high).all()  # clipped: the spread passes 0
    assert lines.count(0.25) == 2 * 3  # a faint path per seed and variant


def test_one_seeds_curves_promise_no_band(tmp_path, monkeypatch):
    """A run of one seed has no interval: no band is drawn and the legend says so, in the
    singular."""
    legends, bands = [], []
    legend, fill_between = plots.Figure.legend, Axes.fill_between

    def spy_legend(self, handles, labels, **kwargs):
        legends.append((list(labels), kwargs.get("title")))
        return legend(self, handles, labels, **kwargs)

    def spy_fill_between(self, *args, **kwargs):
        bands.append(args)
        return fill_between(self, *args, **kwargs)

    monkeypatch.setattr(plots.Figure, "legend", spy_legend)
    monkeypatch.setattr(Axes, "fill_between", spy_fill_between)
    curves = plots.Curves()
    curves.add("ccr", [0, 100_000], {"success_rate": np.array([[0.0, 0.5]])})
    plots.draw_curves(curves, tmp_path / "curves.png", metrics=("success_rate",))
    assert legends == [(["ccr (n=1 seed)"], "one seed: no interval")]
    assert bands == []
