"""The tables' figures from their cells: progress (danger against return), training
curves, the same hidden-obstacle episode by both teams, and the followers' distances."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from ccrjax.envs.scenarios import Layout
from ccrjax.run.folder import replacing
from ccrjax.viz.plots import (
    VARIANT_COLOURS,
    Curves,
    draw_curves,
    draw_obstacle_distances,
    draw_progress_matched,
)
from ccrjax.viz.record import CCR_STATE_COLOURS, CCR_STATE_NAMES, EpisodeRecord
from ccrjax.viz.render import draw_episode
from experiments import protocol
from experiments.paper import PAPER_SCENARIOS
from experiments.tables_grid import LEARNER_NAMES, SCENARIO_NAMES, VARIANT_SUFFIX, VARIANTS


def draw_figures(cells, out: Path, quick: bool = False) -> list[Path]:
    """The tables' figures from the cells (``quick``: every title says the quick mode)."""
    note = protocol.QUICK_FIGURE if quick else ""
    written = []
    algos = tuple(dict.fromkeys(algo for _, algo, _ in cells))  # the family the cells hold
    for scenario in PAPER_SCENARIOS:
        panels = {}
        for algo in algos:
            panels[LEARNER_NAMES[algo]] = {
                variant: (np.asarray(cells[(scenario, algo, variant)]["history"]["return"]),
                          np.asarray(cells[(scenario, algo, variant)]["history"]
                                     ["danger_frequency"]))
                for variant in VARIANTS}
        path = out / f"progress_{scenario}.png"
        draw_progress_matched(panels, path, title=f"{note}{SCENARIO_NAMES[scenario]}: dangerous-"
                              "behaviour frequency against return along training")
        written.append(path)
    metrics = ("return", "danger_frequency", "success_rate", "learning_danger_steps")
    for scenario in PAPER_SCENARIOS:
        for algo in algos:
            curves = Curves()
            for variant in VARIANTS:
                cell = cells[(scenario, algo, variant)]
                steps = np.asarray(cell["history"]["env_steps"][0])
                curves.add(LEARNER_NAMES[algo] + VARIANT_SUFFIX[variant], steps,
                           {m: np.asarray(cell["history"][m]) for m in metrics},
                           colour=VARIANT_COLOURS[variant])  # as in the progress figures
            path = out / f"curves_{scenario}_{algo}.png"
            draw_curves(curves, path, metrics=metrics,
                        title=f"{note}{SCENARIO_NAMES[scenario]}, {LEARNER_NAMES[algo]}: plain, "
                        "pessimistic and CCR during training")
            written.append(path)
    if "maddpg" not in algos:
        return written
    plain = cells[("hidden_obstacle", "maddpg", "plain")]
    ccr = cells[("hidden_obstacle", "maddpg", "ccr")]
    path = out / "trajectories_hidden_obstacle_maddpg.png"
    draw_trajectories(plain, ccr, path, note)
    written.append(path)
    path = out / "distance_hidden_obstacle_maddpg.png"
    draw_obstacle_distances(np.asarray(plain["arrival"]["centre_distance"]),
                            np.asarray(ccr["arrival"]["centre_distance"]), path, note)
    written.append(path)
    return written


def _record(cell: dict) -> EpisodeRecord:
    episode = cell["episode"]
    positions = np.asarray(episode["position"])  # [T + 1, N, 2]
    states = np.zeros(positions.shape[:2], np.int32)
    if episode["ccr_state"] is not None:
        states[1:] = np.asarray(episode["ccr_state"])
    layout = Layout()
    return EpisodeRecord(
        scenario="hidden_obstacle", positions=positions, robot_radius=0.05,
        goal=layout.goal, goal_radius=layout.goal_radius,
        hazard_centre=np.asarray(episode["hazard_centre"]),
        hazard_half_extent=np.asarray(episode["hazard_half_extent"]),
        hazard_direction=np.zeros(2), states=states,
        state_names=CCR_STATE_NAMES, state_colours=CCR_STATE_COLOURS,
        danger=np.concatenate([np.zeros((1, positions.shape[1]), bool),
                               np.asarray(episode["danger"], bool)]),
        caption=f"seed {cell['seeds'][0]}, the first recorded evaluation episode",
    )


def draw_trajectories(plain: dict, ccr: dict, path: Path, note: str = "") -> None:
    """The same evaluation episode (same starts, same obstacle) by both teams, side by side
    (``note`` before each label)."""
    images = []
    with tempfile.TemporaryDirectory() as folder:
        for name, cell in (("plain", plain), ("ccr", ccr)):
            file = Path(folder) / f"{name}.png"
            draw_episode(_record(cell), file, dpi=90)
            images.append(Image.open(file).convert("RGB"))
        width = sum(image.width for image in images)
        height = max(image.height for image in images)
        canvas = Image.new("RGB", (width, height + 40), "white")
        draw = ImageDraw.Draw(canvas)
        font = ImageFont.load_default(size=22)
        x = 0
        for image, label in zip(images, ("MADDPG (CCR not running: all standby)",
                                         "MADDPG+CCR (CCR's colours)"), strict=True):
            canvas.paste(image, (x, 40))
            draw.text((x + 20, 8), note + label, fill="black", font=font)
            x += image.width
        with replacing(path) as temporary:
            canvas.save(temporary)

