"""Pictures of one episode: a still of the trajectories and an animated GIF, drawn with
numpy and matplotlib from an :class:`ccrjax.viz.record.EpisodeRecord` (one environment of
the batch, time axis first)::

    record = record_episode(env, policy, jax.random.key(0))   # ccrjax.viz.record
    draw_episode(record, "runs/demo/turbulence.png")
    animate_episode(record, "runs/demo/turbulence.gif")

Robots are coloured by their per-step state (the record's ``state_colours``).

Matplotlib is used through ``Figure`` and the Agg canvas directly, never
``pyplot``, so nothing here needs a display or changes the global backend.
"""

from __future__ import annotations

import os
import textwrap
from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib import colors as mcolors
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle, FancyArrowPatch, Patch, Rectangle
from PIL import Image

from ccrjax.viz.record import EpisodeRecord

__all__ = ["animate_episode", "characters_per_line", "draw_episode"]

# One colour per robot (trajectories), repeated beyond eight robots; none near the CCR
# states' blue, yellow and pink (the points along a path) or the danger rings' dark red.
ROBOT_COLOURS: tuple[str, ...] = ("#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#17becf",
                                  "#7f7f7f", "#393b79", "#637939")
DANGER_COLOUR = "#8b0015"  # darker than the failure cross (FAILURE_COLOUR)

SCENARIO_TITLES = {
    "turbulence": "Turbulence",
    "strong_wind": "Strong wind",
    "hidden_obstacle": "Hidden obstacle",
    "nominal": "Nominal (no hazard)",
}
HAZARD_COLOURS = {
    "turbulence": "#e8743b",
    "strong_wind": "#4fb6c9",
    "hidden_obstacle": "#6b6b6b",
    "nominal": "#9a9a9a",
}
GOAL_COLOUR = "#2ca02c"
FAILURE_COLOUR = "#d62728"
TRAIL_COLOUR = "#8c8c8c"


# --------------------------------------------------------------------------- drawing
def _extent(record: EpisodeRecord, margin: float = 0.25) -> tuple[float, float, float, float]:
    """Axis limits holding the robots, the hazard and the target, with a margin."""
    xs = [record.positions[..., 0].min(), record.positions[..., 0].max()]
    ys = [record.positions[..., 1].min(), record.positions[..., 1].max()]
    reach = record.goal_radius
    xs += [record.goal[0] - reach, record.goal[0] + reach]
    ys += [record.goal[1] - reach, record.goal[1] + reach]
    half = record.hazard_half_extent
    xs += [record.hazard_centre[0] - half[0], record.hazard_centre[0] + half[0]]
    ys += [record.hazard_centre[1] - half[1], record.hazard_centre[1] + half[1]]
    pad = margin + record.robot_radius
    return min(xs) - pad, max(xs) + pad, min(ys) - pad, max(ys) + pad


def _draw_hazard(ax: Any, record: EpisodeRecord) -> list[Any]:
    """Draws the scenario's hazard and returns its legend handles."""
    centre, half = record.hazard_centre, record.hazard_half_extent
    colour = HAZARD_COLOURS.get(record.scenario, "#9a9a9a")
    corner = (centre[0] - half[0], centre[1] - half[1])
    if record.scenario == "turbulence":
        ax.add_patch(Circle(tuple(centre), half[0], facecolor=colour, alpha=0.25,
                            edgecolor=colour, linewidth=1.5, zorder=1))
        return [Patch(facecolor=colour, alpha=0.35, edgecolor=colour, label="turbulence area")]
    if record.scenario == "strong_wind":
        ax.add_patch(Rectangle(corner, 2 * half[0], 2 * half[1], facecolor=colour, alpha=0.25,
                               edgecolor=colour, linewidth=1.5, zorder=1))
        direction = record.hazard_direction
        norm = float(np.hypot(*direction))
        if norm > 0:
            arm = 0.75 * float(min(half)) * direction / norm
            ax.add_patch(FancyArrowPatch(tuple(centre - arm), tuple(centre + arm),
                                         arrowstyle="-|>", mutation_scale=18, linewidth=2.2,
                                         color="#1d6f80", zorder=2))
        wind = Line2D([], [], color="#1d6f80", marker=">", linewidth=2, label="wind direction")
        area = Patch(facecolor=colour, alpha=0.35, edgecolor=colour, label="strong wind area")
        return [area, wind]
    if record.scenario == "hidden_obstacle":
        ax.add_patch(Rectangle(corner, 2 * half[0], 2 * half[1], facecolor=colour, alpha=0.55,
                               edgecolor="none", zorder=1))
        ax.add_patch(Rectangle(corner, 2 * half[0], 2 * half[1], facecolor="none",
                               edgecolor="#333333", linestyle="--", linewidth=1.5,
                               hatch="//", zorder=1))
        return [Patch(facecolor=colour, alpha=0.6, edgecolor="#333333", linestyle="--",
                      hatch="//", label="hidden obstacle")]
    ax.plot(*centre, marker="x", color=colour, markersize=9, alpha=0.6, linestyle="none",
            zorder=1)
    return [Line2D([], [], marker="x", color=colour, alpha=0.6, linestyle="none",
                   label="virtual hazard centre")]


def _draw_target(ax: Any, record: EpisodeRecord) -> list[Any]:
    """Draws the target area (success: inside it at the end) and returns its legend handle."""
    ax.add_patch(Circle(record.goal, record.goal_radius, facecolor=GOAL_COLOUR, alpha=0.2,
                        edgecolor=GOAL_COLOUR, linewidth=1.5, zorder=1))
    return [Patch(facecolor=GOAL_COLOUR, alpha=0.3, edgecolor=GOAL_COLOUR,
                  label="target area")]


def _draw_outcomes(ax: Any, record: EpisodeRecord, size: float) -> list[Any]:
    """Marks each robot's end: a green ring if it succeeded, a red cross if not."""
    end = record.positions[-1]
    ok = record.succeeded
    if ok.any():
        ax.plot(end[ok, 0], end[ok, 1], marker="o", markersize=size, markerfacecolor="none",
                markeredgecolor=GOAL_COLOUR, markeredgewidth=1.8, linestyle="none", zorder=7)
    if (~ok).any():
        ax.plot(end[~ok, 0], end[~ok, 1], marker="x", markersize=size, color=FAILURE_COLOUR,
                markeredgewidth=2.0, linestyle="none", zorder=7)
    return _outcome_handles(record)


def _outcome_handles(record: EpisodeRecord) -> list[Any]:
    """The legend entries of :func:`_draw_outcomes`, with how many robots each marks."""
    ok = record.succeeded
    return [
        Line2D([], [], marker="o", markerfacecolor="none", markeredgecolor=GOAL_COLOUR,
               markeredgewidth=1.8, linestyle="none", label=f"succeeded ({int(ok.sum())})"),
        Line2D([], [], marker="x", color=FAILURE_COLOUR, markeredgewidth=2.0,
               linestyle="none", label=f"failed ({int((~ok).sum())})"),
    ]


def _new_figure(
    record: EpisodeRecord, width: float, legend: float, dpi: int, title_size: float
) -> tuple[Figure, Any, list[Any]]:
    """A figure ``width`` inches wide: equal-aspect axes, then a legend column on the right.

    The height follows the data's aspect ratio (within bounds), so that the axes
    fill their width without empty bands; the title (:func:`_title`, at ``title_size``
    points) is wrapped to the axes' width and the top margin holds its lines. Returns the
    figure, the axes with the hazard, target and title drawn, and their legend handles.
    """
    left, right, bottom = 0.65, legend + 0.15, 0.5  # margins, inches
    axes_width = width - left - right
    title = _title(record, max(20, characters_per_line(axes_width, title_size)))
    # A line is 1.25 em high, plus room above and below.
    top = 0.15 + (title.count("\n") + 1) * 1.25 * title_size / 72
    x0, x1, y0, y1 = _extent(record)
    axes_height = float(np.clip(axes_width * (y1 - y0) / (x1 - x0), 1.5, 1.2 * width))
    height = axes_height + bottom + top
    fig = Figure(figsize=(width, height), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((left / width, bottom / height, axes_width / width, axes_height / height))
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal", anchor="W")
    ax.grid(True, color="#e6e6e6", linewidth=0.6, zorder=0)
    ax.set_axisbelow(True)
    ax.set_xlabel("x", labelpad=1)
    ax.set_ylabel("y", labelpad=1)
    ax.set_title(title, fontsize=title_size)
    handles = _draw_hazard(ax, record) + _draw_target(ax, record)
    return fig, ax, handles


def _add_legend(fig: Figure, handles: list[Any], legend: float, fontsize: float) -> None:
    """The legend in the right-hand column reserved by :func:`_new_figure`."""
    width, height = fig.get_size_inches()
    fig.legend(handles=handles, loc="upper left", fontsize=fontsize, frameon=False,
               bbox_to_anchor=(1.0 - legend / width, 1.0 - 0.35 / height), borderaxespad=0.0,
               handletextpad=0.4)


def _state_handles(record: EpisodeRecord, used_only: bool = False) -> list[Any]:
    used = set(np.unique(record.states).tolist()) if used_only else None
    return [
        Line2D([], [], marker="o", color=colour, markeredgecolor="white", linestyle="none",
               markersize=8, label=name)
        for index, (name, colour) in enumerate(zip(record.state_names, record.state_colours,
                                                   strict=True))
        if used is None or index in used
    ]


def characters_per_line(width: float, points: float) -> int:
    """How many characters of text at ``points`` fit in ``width`` inches (about 0.55 em
    per character), the width to wrap a title to."""
    return int(width * 72 / (0.55 * points))


def _title(record: EpisodeRecord, width: int) -> str:
    """The scenario, team and length, then the caption, in lines of at most ``width``
    characters."""
    name = SCENARIO_TITLES.get(record.scenario, record.scenario)
    text = f"{name}: {record.num_robots} robots, {record.num_steps} steps"
    lines = [text, *textwrap.wrap(record.caption, width)] if record.caption else [text]
    return "\n".join(lines)


def robot_colour(robot: int) -> str:
    return ROBOT_COLOURS[robot % len(ROBOT_COLOURS)]


def _robot_handles(record: EpisodeRecord) -> list[Any]:
    """A line per robot (its trajectory's colour), and the danger mark if it is drawn."""
    handles = [Line2D([], [], color=robot_colour(r), linewidth=2, label=f"robot {r + 1}")
               for r in range(min(record.num_robots, len(ROBOT_COLOURS)))]
    if record.danger is not None:
        handles.append(Line2D([], [], marker="o", markerfacecolor="none", linestyle="none",
                              markeredgecolor=DANGER_COLOUR, markeredgewidth=1.5, markersize=8,
                              label="in danger"))
    return handles


def draw_episode(record: EpisodeRecord, path_png: str | os.PathLike[str], *,
                 dpi: int = 150) -> None:
    """Draws the whole episode to a PNG: hazard, target, and every robot's trajectory.

    Each robot's path is a line in its own colour with a point per step (in the colour
    of the robot's state at that step when there are several states, as under CCR), a
    red ring on every step it spent in danger (when ``record.danger`` is given, whatever
    the transform); a square in its colour marks its start and a disc of its real radius
    its end, ringed in green if the robot ends in the target area (a success) and
    crossed in red if not.
    """
    fig, ax, handles = _new_figure(record, 9.0, 2.0, dpi, 10)
    colours = np.array([mcolors.to_rgba(c) for c in record.state_colours])
    positions = record.positions
    several_states = len(record.state_names) > 1
    for robot in range(record.num_robots):
        path = positions[:, robot]
        colour = robot_colour(robot)
        ax.plot(path[:, 0], path[:, 1], color=colour, linewidth=1.3, alpha=0.9, zorder=3)
        dots = colours[record.states[:, robot]] if several_states else colour
        ax.scatter(path[:, 0], path[:, 1], s=11, c=dots, edgecolors="none", zorder=4)
        if record.danger is not None and record.danger[:, robot].any():
            hit = path[record.danger[:, robot]]
            ax.scatter(hit[:, 0], hit[:, 1], s=42, facecolors="none",
                       edgecolors=DANGER_COLOUR, linewidths=1.2, zorder=4.5)
        ax.plot(*path[0], marker="s", markersize=7, markerfacecolor="white",
                markeredgecolor=colour, markeredgewidth=1.6, linestyle="none", zorder=5)
        ax.add_patch(Circle(tuple(path[-1]), record.robot_radius,
                            facecolor=colours[record.states[-1, robot]] if several_states
                            else colour, edgecolor="black", linewidth=1.2, zorder=6))
    handles = _robot_handles(record) + (_state_handles(record) if several_states else []) + [
        Line2D([], [], marker="s", markerfacecolor="white", markeredgecolor="black",
               linestyle="none", label="start"),
        Line2D([], [], marker="o", markerfacecolor="#dddddd", markeredgecolor="black",
               markersize=9, linestyle="none",
               label="end (robot size, in its\nlast state's colour)" if several_states
               else "end (robot size, in its colour)"),
    ] + _draw_outcomes(ax, record, 12) + handles
    _add_legend(fig, handles, 2.0, 8)
    fig.savefig(os.fspath(path_png), dpi=dpi)


def _palette(frame: np.ndarray, colours: Sequence[Any], size: int = 64) -> np.ndarray:
    """One GIF palette ``uint8[size, 3]`` for every frame: exact ``colours`` plus the frame's.

    White, black and ``colours`` are kept exactly, with a few blends towards
    white for anti-aliased edges; median cut of ``frame`` (the first one) fills
    the rest. A shared palette makes frames differ only where robots move, so
    the GIF encoder stores small changed rectangles instead of whole frames.
    """
    exact = [(255, 255, 255), (0, 0, 0)]
    for colour in colours:
        rgb = np.array(mcolors.to_rgb(colour)) * 255
        for weight in (1.0, 0.6, 0.3):
            blend = tuple(int(round(v)) for v in weight * rgb + (1 - weight) * 255)
            if blend not in exact:
                exact.append(blend)
    exact = exact[: size - 8]
    rest = Image.fromarray(frame).quantize(
        colors=size - len(exact), method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE
    )
    rest_rgb = np.array(rest.getpalette()[: 3 * (size - len(exact))], np.uint8).reshape(-1, 3)
    return np.concatenate([np.array(exact, np.uint8), rest_rgb])


def _indexed(frame: np.ndarray, palette: np.ndarray) -> Image.Image:
    """``frame`` ``uint8[H, W, 3]`` as a palette image, each pixel its nearest palette colour.

    Exact nearest colours (Pillow's own mapping is approximate and turns white
    into off-white), computed once per distinct colour of the frame.
    """
    packed = (frame[..., 0].astype(np.int32) << 16) | (frame[..., 1].astype(np.int32) << 8)
    packed |= frame[..., 2]
    unique, inverse = np.unique(packed.ravel(), return_inverse=True)
    rgb = np.stack([unique >> 16, (unique >> 8) & 255, unique & 255], axis=-1)
    distance = ((rgb[:, None, :] - palette[None].astype(np.int32)) ** 2).sum(axis=-1)
    index = distance.argmin(axis=1).astype(np.uint8)[inverse].reshape(frame.shape[:2])
    image = Image.fromarray(index, mode="P")
    image.putpalette(palette.ravel().tolist())
    return image


def _outcome_artists(ax: Any, record: EpisodeRecord) -> list[Any]:
    """The end markers of :func:`_draw_outcomes`, as artists drawn on the last frame only."""
    before = set(ax.lines)
    _draw_outcomes(ax, record, 10)
    return [line for line in ax.lines if line not in before]


def animate_episode(record: EpisodeRecord, path_gif: str | os.PathLike[str], *,
                    fps: int = 10, dpi: int = 100, trail: int | None = None) -> None:
    """Writes the episode as an animated GIF with one frame per recorded step.

    Robots are discs of their real radius, coloured by their current state (by robot
    when there is one state), outlined in red while in danger, each followed by a trail
    in its own colour of its last ``trail`` steps (all by default); the last frame marks
    each robot's outcome, and the legend says how many succeeded and failed.
    Frames share one 64-colour palette, which keeps 50 steps well below 2 MB.
    """
    if isinstance(fps, bool) or not isinstance(fps, int) or not 1 <= fps <= 100:
        raise ValueError(f"fps must be an integer in [1, 100], got {fps!r}")
    if trail is not None and (isinstance(trail, bool) or not isinstance(trail, int) or trail < 0):
        raise ValueError(f"trail must be None or an integer >= 0, got {trail!r}")
    fig, ax, handles = _new_figure(record, 6.4, 1.45, dpi, 9)
    canvas = fig.canvas
    several_states = len(record.state_names) > 1
    _add_legend(fig, _robot_handles(record) + (_state_handles(record) if several_states else [])
                + [*_outcome_handles(record), *handles], 1.45, 7)
    colours = [mcolors.to_rgba(c) for c in record.state_colours]
    positions = record.positions
    trails = [ax.plot([], [], color=robot_colour(robot), linewidth=1.0, zorder=3)[0]
              for robot in range(record.num_robots)]
    discs = [ax.add_patch(Circle(tuple(positions[0, robot]), record.robot_radius,
                                 edgecolor="black", linewidth=0.8, zorder=5))
             for robot in range(record.num_robots)]
    clock = ax.text(0.01, 0.99, "", transform=ax.transAxes, ha="left", va="top", fontsize=8,
                    family="monospace", zorder=7)

    # Blitting: draw the static picture (and settle the layout) once, then per frame
    # restore it and draw only the moving artists, about ten times faster.
    moving = [*trails, *discs, clock]
    for artist in moving:
        artist.set_animated(True)
    canvas.draw()
    background = canvas.copy_from_bbox(fig.bbox)

    palette = None
    frames = []
    for step in range(record.num_steps + 1):
        start = 0 if trail is None else max(0, step - trail)
        for robot in range(record.num_robots):
            path = positions[start:step + 1, robot]
            trails[robot].set_data(path[:, 0], path[:, 1])
            discs[robot].center = tuple(positions[step, robot])
            discs[robot].set_facecolor(colours[record.states[step, robot]] if several_states
                                       else robot_colour(robot))
            in_danger = record.danger is not None and record.danger[step, robot]
            discs[robot].set_edgecolor(DANGER_COLOUR if in_danger else "black")
            discs[robot].set_linewidth(1.8 if in_danger else 0.8)
        clock.set_text(f"t = {step:3d}")
        canvas.restore_region(background)
        for artist in moving:
            ax.draw_artist(artist)
        if step == record.num_steps:
            for artist in _outcome_artists(ax, record):
                ax.draw_artist(artist)
        rgb = np.asarray(canvas.buffer_rgba())[..., :3].copy()
        if palette is None:
            palette = _palette(rgb, [*record.state_colours, *ROBOT_COLOURS, DANGER_COLOUR,
                                     TRAIL_COLOUR, GOAL_COLOUR, FAILURE_COLOUR])
        frames.append(_indexed(rgb, palette))
    duration = round(1000 / fps)
    # Hold the last frame (with the outcomes marked) a second longer.
    frames.append(frames[-1])
    frames[0].save(os.fspath(path_gif), save_all=True, append_images=frames[1:],
                   duration=duration, loop=0, optimize=False, disposal=1)
