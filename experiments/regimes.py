"""The information regimes: ``python experiments/calibrate.py --regimes``.

CCR's argument is about information: a teammate's trouble should tell a robot something it
could not know otherwise. Whether it can depends on the task's regime, set by two knobs of
:class:`ccrjax.envs.scenarios.Layout`: the hazard's **placement** (its centre's height
drawn in ``[-h, h]``: today's ``h = 0.25`` is almost the same place every episode, so a
fixed detour learnt by heart avoids it; wider ranges make it impossible to memorise) and
the team's **formation** (abreast, the robots meet the hazard together and nobody can
warn anyone; or a column, ``column_spacing`` apart along the way, the robots meet it one
after another). For the hidden obstacle, turbulence and strong wind, over placements
``h`` in :data:`PLACEMENTS` (x stays in ``[-0.1, 0.1]``) and the formations of
:data:`FORMATIONS`, this measures success and danger of five reference controllers
(``reference_controllers.py``, ``information_controllers.py``):

* ``go_to_goal`` (hazard-blind), ``oracle`` (knows the hazard): the bounds;
* ``self_reactive`` (only what the robot senses itself) and ``team_informed`` (plus what
  CCR shares, with perfect detection: teammates' dangers within ``comm_range`` over the
  last ``window`` steps, CCR's defaults): the worth of the team's information;
* ``memoriser`` (senses nothing; the one fixed detour through ``(0, y_w)`` that is best
  on average): the worth of knowing where hazards usually are. ``y_w`` is chosen from
  the grid ``information_controllers.memoriser_heights`` on ``--select-episodes`` episodes
  of the **selection seed** ``--selection-seed``, never the evaluation seed: the lowest
  danger among the heights whose success is within 10 points of the oracle's (on the same
  episodes), else the highest success (``information_controllers.choose_height``);

and the share of go-to-goal's dangerous robot-steps that a teammate in range forewarned at
least :data:`FOREWARNING_LEAD` steps earlier (``ccr_signal.forewarning``): how much warning
the regime leaves to a reflex at all.

**Episode length** per formation, chosen on go-to-goal alone: the smallest length at which
go-to-goal reaches :data:`LENGTH_SUCCESS` success on ``nominal`` with that layout, times
:data:`LENGTH_FACTOR` (today's 25 / 19), rounded up to a multiple of :data:`LENGTH_MULTIPLE`
(today's abreast regime keeps 25). A column whose last robot starts beyond the arena gets a
larger ``arena_half_extent`` (x).

A regime is **informative** (:func:`informative`) when the team's information halves the
danger at equal success AND a memorised detour is clearly worse than knowing the hazard:
the thresholds are :data:`INFORMED_DANGER_RATIO`, :data:`EQUAL_SUCCESS`,
:data:`MEMORISER_MARGIN` and :data:`MEMORISER_RATIO`.

Each (scenario, layout) is one compiled program: the five controllers drive blocks of one
batch (``information_controllers.in_blocks``), and the memoriser's selection runs in the
same program, ``vmap``-ed over the heights (every height on the same selection episodes),
its choice made on the device (``choose_height`` is traceable). Writes
``<out>/regimes.md`` and ``regimes.json``.
"""

from __future__ import annotations

import math
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ccrjax.envs.env import ROBOT_RADIUS, EmergencyEnv
from ccrjax.envs.scenarios import Layout
from ccrjax.training.acting import Episode, episode_metrics, run_episode
from ccrjax.transforms import Plain
from ccrjax.transforms.ccr import CCRConfig
from experiments.ccr_signal import forewarned_steps, forewarning
from experiments.information_controllers import (
    choose_height,
    in_blocks,
    memoriser,
    memoriser_heights,
    self_reactive,
    team_informed,
)
from experiments.reference_controllers import go_to_goal, oracle

REGIME_SCENARIOS = ("hidden_obstacle", "turbulence", "strong_wind")
PLACEMENTS = (0.25, 0.5, 1.0)  # half-ranges h of the hazard centre's height, [-h, h]
FORMATIONS = (("abreast", None), ("column", 0.3), ("column", 0.45), ("column", 0.6),
              ("column", 0.9))  # (formation, spacing); 0.9: the follower just in CCR's range
ROWS = ("go_to_goal", "self_reactive", "team_informed", "oracle", "memoriser")
NUM_ROBOTS = 5

LENGTH_SUCCESS = 0.95  # go-to-goal's success on nominal that sets the episode length
LENGTH_FACTOR = 1.3  # today's 25 steps / the 19 go-to-goal needs
LENGTH_MULTIPLE = 5
LENGTH_PROBE = 150  # steps of the nominal run that finds the length

INFORMED_DANGER_RATIO = 0.5
EQUAL_SUCCESS = 0.05
MEMORISER_MARGIN = 0.05
MEMORISER_RATIO = 2.0
FOREWARNING_LEAD = 2
"""The issue's thresholds ("A valid experiment": reference controllers that measure what the
team's information is worth): a regime is informative when team_informed's danger is at
most ``INFORMED_DANGER_RATIO`` x self_reactive's with their successes within
``EQUAL_SUCCESS`` of each other, and the memoriser's danger is at least the oracle's +
``MEMORISER_MARGIN`` and at least ``MEMORISER_RATIO`` x the oracle's; the forewarning share
counts leads of at least ``FOREWARNING_LEAD`` steps."""


def regime_layout(placement: float, formation: str, spacing: float | None) -> Layout:
    """Today's layout with the hazard's height drawn in ``[-placement, placement]`` and the
    formation; a column whose last robot would start beyond the arena gets an arena long
    enough (x half extent rounded up to 0.05)."""
    base = Layout()
    params: dict[str, Any] = {"hazard_y_range": (-placement, placement)}
    if formation == "column":
        last = base.start_centre[0] + base.start_half_extent[0] - (NUM_ROBOTS - 1) * spacing
        needed = math.ceil((ROBOT_RADIUS - last) * 20 - 1e-6) / 20 + 0.05
        params.update(formation="column", column_spacing=spacing,
                      arena_half_extent=(max(base.arena_half_extent[0], needed),
                                         base.arena_half_extent[1]))
    return Layout(**params)


def choose_length(layout: Layout, episodes: int, seed: int) -> dict[str, int]:
    """The episode length of a formation (module docstring), from one go-to-goal run of
    :data:`LENGTH_PROBE` steps on ``nominal`` (the controller ignores the clock, so step
    ``t`` of a long episode is step ``t`` of any longer than ``t``)."""
    env = EmergencyEnv("nominal", num_robots=NUM_ROBOTS, num_envs=episodes, layout=layout,
                 episode_length=LENGTH_PROBE)
    transform = Plain()
    success = jax.jit(lambda key: jnp.mean(run_episode(
        env, transform, transform.init(env), None, False, key,
        controller=go_to_goal(env))[1].success, axis=(1, 2)))(jax.random.PRNGKey(seed))
    reached = np.flatnonzero(np.asarray(success) >= LENGTH_SUCCESS)
    if reached.size == 0:
        raise RuntimeError(f"go_to_goal never reached {LENGTH_SUCCESS:.0%} success in "
                           f"{LENGTH_PROBE} steps with layout {layout}")
    needed = int(reached[0]) + 1  # success[t] is the state after t + 1 steps
    length = LENGTH_MULTIPLE * math.ceil(LENGTH_FACTOR * needed / LENGTH_MULTIPLE - 1e-9)
    return {"go_to_goal_steps": needed, "episode_length": length}


def _block(episode: Episode, index: int, size: int) -> Episode:
    part = slice(index * size, (index + 1) * size)
    return Episode(transitions=None, env_reward=episode.env_reward[..., part],
                   danger=episode.danger[..., part], success=episode.success[..., part],
                   target_distance=episode.target_distance[..., part],
                   hazard_distance=episode.hazard_distance[..., part],
                   position=episode.position[..., part], hazard=None, info={})


def regime_program(scenario: str, layout: Layout, episode_length: int, episodes: int,
                   select_episodes: int):
    """``(heights, program)``: ``program(eval_key, select_key, heights)``, one compiled
    program, returns the five controllers' metrics on ``episodes`` episodes of
    ``eval_key``, go-to-goal's per-step danger and positions, and the memoriser's
    selection on ``select_episodes`` episodes of ``select_key`` (every height of
    ``heights`` and the oracle on the same episodes) with the chosen index."""
    def env_of(batch: int) -> EmergencyEnv:
        return EmergencyEnv(scenario, num_robots=NUM_ROBOTS, num_envs=batch, layout=layout,
                      episode_length=episode_length)

    evaluation, selection = env_of(len(ROWS) * episodes), env_of(select_episodes)
    transform = Plain()

    def play(env: EmergencyEnv, controller, key: jax.Array) -> Episode:
        return run_episode(env, transform, transform.init(env), None, False, key,
                           controller=controller)[1]

    def program(eval_key: jax.Array, select_key: jax.Array, heights: jax.Array):
        def height_metrics(y_w):
            episode = play(selection, memoriser(selection, y_w), select_key)
            return jnp.mean(episode.success[-1]), jnp.mean(episode.danger)

        success, danger = jax.vmap(height_metrics)(heights)
        oracle_success = jnp.mean(play(selection, oracle(selection), select_key).success[-1])
        chosen = choose_height(heights, success, danger, oracle_success)
        controllers = [go_to_goal(evaluation), self_reactive(evaluation),
                       team_informed(evaluation), oracle(evaluation),
                       memoriser(evaluation, heights[chosen])]
        episode = play(evaluation, in_blocks(controllers, episodes), eval_key)
        metrics = {name: episode_metrics(_block(episode, k, episodes))
                   for k, name in enumerate(ROWS)}
        blind = _block(episode, 0, episodes)
        return {"metrics": metrics, "danger": blind.danger > 0.5, "position": blind.position,
                "selection": {"success": success, "danger": danger,
                              "oracle_success": oracle_success, "chosen": chosen}}

    return memoriser_heights(selection), jax.jit(program)


def forewarned_share(danger: np.ndarray, position: np.ndarray) -> float | None:
    """Share of dangerous robot-steps ``danger`` ``[T, N, E]`` whose spell a teammate within
    CCR's ``comm_range`` forewarned at least :data:`FOREWARNING_LEAD` steps earlier
    (``ccr_signal.forewarning``, CCR's window); ``position`` ``[T + 1, N, 2, E]``."""
    if not danger.any():
        return None
    config = CCRConfig()
    after = position[1:]  # the states the danger flags describe
    offset = after[:, :, None] - after[:, None, :]  # [T, N, N, 2, E]
    distance = np.hypot(offset[:, :, :, 0], offset[:, :, :, 1])
    robots = np.arange(distance.shape[1])
    distance[:, robots, robots] = np.inf
    lead = forewarning(danger, distance, config.comm_range, config.window)
    return float(forewarned_steps(danger, lead, FOREWARNING_LEAD).sum() / danger.sum())


def informative(rows: dict[str, dict[str, float]]) -> dict[str, bool]:
    """The issue's two conditions and their conjunction (thresholds: module constants)."""
    own, team = rows["self_reactive"], rows["team_informed"]
    known, memorised = rows["oracle"], rows["memoriser"]
    equal = equal_success(rows)
    # Nothing to halve where self_reactive is never in danger.
    halved = own["danger_frequency"] > 0 and (
        team["danger_frequency"] <= INFORMED_DANGER_RATIO * own["danger_frequency"] + 1e-9)
    worse = (memorised["danger_frequency"] >= known["danger_frequency"] + MEMORISER_MARGIN - 1e-9
             and memorised["danger_frequency"]
             >= MEMORISER_RATIO * known["danger_frequency"] - 1e-9)
    return {"team_halves_danger": bool(equal and halved), "memoriser_clearly_worse": bool(worse),
            "informative": bool(equal and halved and worse)}


def danger_ratio(regime: dict[str, Any]) -> float:
    """team_informed's danger over self_reactive's (inf where self_reactive is never in
    danger): how much of its own danger a teammate's trouble spares a robot."""
    own = regime["rows"]["self_reactive"]["danger_frequency"]
    team = regime["rows"]["team_informed"]["danger_frequency"]
    return team / own if own > 0 else math.inf


def choose_regimes(regimes: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per scenario, the regime the study uses: an informative one (the lowest
    :func:`danger_ratio` among them), else the **closest**: the lowest ratio among the
    regimes whose successes are equal and whose memoriser is clearly worse than the oracle
    (both conditions of :func:`informative` but the halving), else among all. Ties go to the
    earlier regime of the grid (narrower placement, abreast, shorter spacing)."""
    chosen = {}
    for scenario in dict.fromkeys(r["scenario"] for r in regimes):
        own = [r for r in regimes if r["scenario"] == scenario]
        pools = ([r for r in own if r["informative"]],
                 [r for r in own if r["memoriser_clearly_worse"] and equal_success(r["rows"])],
                 own)
        pool = next(p for p in pools if p)
        best = min(pool, key=danger_ratio)
        chosen[scenario] = {
            "placement": best["placement"], "formation": best["formation"],
            "column_spacing": best["column_spacing"],
            "arena_half_extent": best["arena_half_extent"],
            "episode_length": best["episode_length"], "danger_ratio": danger_ratio(best),
            "informative": best["informative"],
        }
    return chosen


def equal_success(rows: dict[str, dict[str, float]]) -> bool:
    """team_informed's and self_reactive's successes within ``EQUAL_SUCCESS``."""
    return abs(rows["team_informed"]["success_rate"]
               - rows["self_reactive"]["success_rate"]) <= EQUAL_SUCCESS + 1e-9


def measure_regime(scenario: str, layout: Layout, episode_length: int, episodes: int,
                   seed: int, selection_seed: int, select_episodes: int) -> dict[str, Any]:
    """One regime's rows, forewarning share, memoriser selection and flags."""
    heights, program = regime_program(scenario, layout, episode_length, episodes,
                                      select_episodes)
    out = jax.tree.map(np.asarray, program(jax.random.PRNGKey(seed),
                                           jax.random.PRNGKey(selection_seed),
                                           jnp.asarray(heights)))
    rows = {name: {k: float(v) for k, v in m.items()} for name, m in out["metrics"].items()}
    chosen = int(out["selection"]["chosen"])
    return {
        "scenario": scenario, "placement": float(layout.hazard_y_range[1]),
        "formation": layout.formation,
        "column_spacing": layout.column_spacing if layout.formation == "column" else None,
        "arena_half_extent": list(layout.arena_half_extent),
        "episode_length": episode_length, "rows": rows,
        "forewarned_share": forewarned_share(out["danger"], out["position"]),
        "memoriser": {
            "y_w": float(heights[chosen]), "heights": [float(h) for h in heights],
            "success": [float(v) for v in out["selection"]["success"]],
            "danger": [float(v) for v in out["selection"]["danger"]],
            "oracle_success": float(out["selection"]["oracle_success"]),
        },
        **informative(rows),
    }


def measure_grid(episodes: int, seed: int, selection_seed: int, select_episodes: int,
                 length_episodes: int, scenarios=REGIME_SCENARIOS, placements=PLACEMENTS,
                 formations=FORMATIONS, log=print) -> dict[str, Any]:
    """Every regime of the grid; placements a scenario's validation refuses are listed in
    ``refused`` (with the reason) instead."""
    lengths, regimes, refused = {}, [], []
    for formation, spacing in formations:
        name = formation if spacing is None else f"{formation} {spacing:g}"
        lengths[name] = choose_length(regime_layout(PLACEMENTS[0], formation, spacing),
                                      length_episodes, seed)
        log(f"{name}: go_to_goal needs {lengths[name]['go_to_goal_steps']} steps on nominal; "
            f"episode length {lengths[name]['episode_length']}")
    for scenario in scenarios:
        for placement in placements:
            for formation, spacing in formations:
                name = formation if spacing is None else f"{formation} {spacing:g}"
                layout = regime_layout(placement, formation, spacing)
                length = lengths[name]["episode_length"]
                try:
                    EmergencyEnv(scenario, num_robots=NUM_ROBOTS, layout=layout,
                                 episode_length=length)
                except ValueError as error:
                    refused.append({"scenario": scenario, "placement": placement,
                                    "formation": name, "reason": str(error)})
                    continue
                start = time.time()
                regime = measure_regime(scenario, layout, length, episodes, seed,
                                        selection_seed, select_episodes)
                regime["seconds"] = time.time() - start
                regimes.append(regime)
                log(f"{scenario}, h {placement:g}, {name}: {regime['seconds']:.0f} s")
    return {"lengths": lengths, "regimes": regimes, "refused": refused}


def _pct(value: float | None) -> str:
    return "n/a" if value is None else f"{100 * value:.1f}%"


def chosen_regime_lines(regimes: list[dict[str, Any]]) -> list[str]:
    """One line per scenario: the regime :func:`choose_regimes` picks and its danger ratio."""
    lines = []
    for scenario, regime in choose_regimes(regimes).items():
        formation = regime["formation"] + (
            f" {regime['column_spacing']:g}" if regime["column_spacing"] else "")
        lines.append(
            f"- {scenario}: h {regime['placement']:g}, {formation}, T "
            f"{regime['episode_length']}, arena half extent "
            f"{', '.join(f'{v:g}' for v in regime['arena_half_extent'])}: danger ratio "
            f"{regime['danger_ratio']:.2f}, "
            + ("informative" if regime["informative"] else "**not informative** (the closest)"))
    return lines


def markdown(result: dict[str, Any]) -> str:
    grid = result["grid"]
    lines = [
        "### Information regimes", "",
        f"{result['episodes']} episodes of {NUM_ROBOTS} robots per row (seed "
        f"{result['seed']}); the memoriser's height y_w chosen on {result['select_episodes']} "
        f"episodes of the selection seed {result['selection_seed']}. Cells: success / "
        "danger. h: the hazard centre's height is drawn in [-h, h] (x in [-0.1, 0.1]); T: "
        "episode length. Forewarned: share of go-to-goal's dangerous robot-steps forewarned "
        f"by a teammate in range at least {FOREWARNING_LEAD} steps earlier. Informative: "
        f"team_informed's danger <= {INFORMED_DANGER_RATIO:g} x self_reactive's with "
        f"successes within {100 * EQUAL_SUCCESS:g} points (team), and the memoriser's "
        f"danger >= the oracle's + {100 * MEMORISER_MARGIN:g} points and >= "
        f"{MEMORISER_RATIO:g} x (memoriser).", "",
        "| scenario | h | formation | T | " + " | ".join(ROWS[:-1])
        + " | memoriser (y_w) | forewarned | team | memoriser | informative |",
        "|---|---|---|---|" + "---|" * (len(ROWS) - 1) + "---|---|---|---|---|",
    ]
    for regime in grid["regimes"]:
        rows = regime["rows"]
        formation = regime["formation"] + (
            f" {regime['column_spacing']:g}" if regime["column_spacing"] else "")
        cells = [f"{_pct(rows[n]['success_rate'])} / {_pct(rows[n]['danger_frequency'])}"
                 for n in ROWS]
        cells[-1] += f" ({regime['memoriser']['y_w']:+.1f})"
        lines.append(
            f"| {regime['scenario']} | {regime['placement']:g} | {formation} | "
            f"{regime['episode_length']} | " + " | ".join(cells)
            + f" | {_pct(regime['forewarned_share'])} | "
            + " | ".join("yes" if regime[k] else "no" for k in
                         ("team_halves_danger", "memoriser_clearly_worse"))
            + f" | {'**yes**' if regime['informative'] else 'no'} |")
    lines += ["", "Episode lengths (go-to-goal's steps to 95% success on nominal, x "
              f"{LENGTH_FACTOR:g}, rounded up to a multiple of {LENGTH_MULTIPLE}): "
              + "; ".join(f"{name} {v['go_to_goal_steps']} -> {v['episode_length']}"
                          for name, v in grid["lengths"].items()) + "."]
    for entry in grid["refused"]:
        lines.append(f"Refused: {entry['scenario']}, h {entry['placement']:g}, "
                     f"{entry['formation']}: {entry['reason']}")
    lines += ["", "**The regime per scenario** (`choose_regimes`: an informative one, else the "
              "closest: the lowest team_informed / self_reactive danger ratio among regimes "
              "with equal successes and a memoriser clearly worse than the oracle):", ""]
    lines += chosen_regime_lines(grid["regimes"])
    device = f" on {result['device']}" if result.get("device") else ""
    lines += ["", f"Made by `{result['command']}` at commit `{result['commit']}`{device} "
              f"in {result['seconds']:.0f} s."]
    return "\n".join(lines) + "\n"
