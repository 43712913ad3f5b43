"""What a stored cell depends on, and whether it is what the settings and the code make now.

A cell (one scenario and learner's runs, written by an experiment) records the settings it
was made with and the training its runs had. An experiment skips a cell that is current
(:func:`cell_is_current`: the same :func:`cell_identity` and :func:`training_record`) and
trains again one that is not, saying why (:func:`why_not_current`); the invocations of one
results folder stay together while they make the same cells (:func:`same_cells`).
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any

from ccrjax.training import TrainConfig
from ccrjax.training.config import make_env
from experiments import protocol


def settings_record(settings: Any) -> dict[str, Any]:
    """``settings`` (a dataclass) as it reads back from JSON (tuples become lists), so that
    a record on disk compares equal to the settings that made it. The default regime is
    left out, so that the records of the paper's experiments are those made before
    regimes were settings."""
    record = json.loads(json.dumps(dataclasses.asdict(settings)))
    if record.get("regime") == protocol.DEFAULT_REGIME:
        del record["regime"]
    return record


# Settings that choose which cells an invocation makes, or how they are summarised, but
# not what a cell holds: a cell made by a narrower or wider invocation (or one checked
# against other candidate budgets) is kept, not trained again.
# (``part_seeds`` and ``part_values`` are in the records of cells made before grids were
# spread over processes instead of made in parts.)
NOT_IN_CELLS = ("scenarios", "algos", "candidate_every", "candidate_budgets", "part_seeds",
                "part_values", "controller_episodes")


def folder_settings(record: dict[str, Any]) -> dict[str, Any]:
    """The settings every cell of a results folder shares: the settings ``record`` less
    :data:`NOT_IN_CELLS`, which say what one invocation made there (its scope, kept in its
    own invocation record) and so differ between the invocations of one folder."""
    return {k: v for k, v in record.items() if k not in NOT_IN_CELLS}


def cell_identity(record: dict[str, Any], algo: str, budget: int | None = None
                  ) -> dict[str, Any]:
    """What a cell of learner ``algo`` depends on: the settings ``record`` less
    :data:`NOT_IN_CELLS`, with ``steps`` replaced by the budget its runs trained for
    (``budget``, else ``steps`` or the protocol's budget of ``algo``)."""
    kept = {k: v for k, v in folder_settings(record).items() if k != "steps"}
    kept["budget"] = (protocol.budget(algo, record.get("steps"),
                                      record.get("regime", protocol.DEFAULT_REGIME))
                      if budget is None else budget)
    return kept


# Transform parameters that a grid varies or the settings name (the searched values, the
# tables' selected ones), left out of a cell's training record.
SEARCHED_FIELDS = ("lam", "penalty", "cost_limit")


def training_record(config: TrainConfig) -> dict[str, Any]:
    """What a cell's runs were trained with beyond the settings and the cell's scenario,
    learner and variant, every value resolved (defaults included): the learner's
    hyperparameters (MAAC's action set among them), the team, episode and batch sizes,
    when learning starts, the environment's scenario, layout and physics parameters, and
    the transform's (less :data:`SEARCHED_FIELDS`). Each new cell stores it, so that a cell
    made before one of these changed is trained again, never mixed with newer ones."""
    env = make_env(config, 1)
    transform = dataclasses.asdict(config.resolved_transform)
    transform = transform.get("config", transform)  # CCR's parameters live in its config
    record = {
        "learner": dataclasses.asdict(config.resolved_learner),
        "num_robots": config.num_robots, "episode_length": config.episode_length,
        "num_envs": config.num_envs, "learning_starts": config.learning_starts,
        "transform": {k: v for k, v in transform.items() if k not in SEARCHED_FIELDS},
        "scenario": dataclasses.asdict(env.scenario), "layout": env.layout.record(),
        "physics": dataclasses.asdict(env.physics), "sensitivity": env.sensitivity,
        "robot_radius": env.robot_radius,
    }
    return json.loads(json.dumps(record))


def expected_training(cell: dict[str, Any], record: dict[str, Any]) -> dict[str, Any]:
    """The training record of ``cell``'s scenario, learner and variant under settings
    ``record`` at the current code (the protocol's run configuration, the variant's
    default transform)."""
    variant = cell.get("variant") or record.get("variant") or "plain"
    settings = protocol.Settings(seeds=tuple(record.get("seeds", ())), steps=record.get("steps"),
                                 quick=record.get("quick", False),
                                 regime=record.get("regime", protocol.DEFAULT_REGIME),
                                 eval_every=record["eval_every"],
                                 eval_episodes=record["eval_episodes"])
    return training_record(protocol.run_config(settings, cell["scenario"], cell["algo"],
                                               variant))


def cell_budget(cell: dict[str, Any]) -> int | None:
    """The budget a stored cell trained for: its ``budget``, or for cells written before
    that was recorded, the environment steps of its last evaluation."""
    if "budget" in cell:
        return cell["budget"]
    steps = cell.get("env_steps") or (cell.get("history") or {}).get("env_steps")
    while isinstance(steps, list) and steps and isinstance(steps[-1], list):
        steps = steps[-1]
    return int(steps[-1]) if steps else None


def why_not_current(cell: dict[str, Any] | None, record: dict[str, Any]) -> str | None:
    """Why the stored ``cell`` is not what settings ``record`` would make (``None`` if it
    is): none made, or the settings or training parameters that differ. A cell is current
    with the same :func:`cell_identity` and, for cells that store one (cells made before it
    was stored do not), the same :func:`training_record` as the current code gives."""
    if not cell:
        return "none made"
    if (not isinstance(cell.get("settings"), dict)
            or cell.get("algo") not in protocol.EXPERIMENT_ALGOS):
        return "not a cell"

    def differing(made: dict[str, Any], wanted: dict[str, Any]) -> str:
        return ", ".join(sorted(k for k in made.keys() | wanted.keys()
                                if made.get(k) != wanted.get(k)))

    algo = cell["algo"]
    made, wanted = cell_identity(cell["settings"], algo, cell_budget(cell)), cell_identity(
        record, algo)
    if made != wanted:
        return f"made with other {differing(made, wanted)}"
    if "training" in cell and cell["training"] != (expected := expected_training(cell, record)):
        return (f"trained with other {differing(cell['training'], expected)} than the code "
                "now gives")
    return None


def cell_is_current(cell: dict[str, Any] | None, record: dict[str, Any]) -> bool:
    """Whether the stored ``cell`` is what settings ``record`` would make
    (:func:`why_not_current`)."""
    return why_not_current(cell, record) is None


def comparable_identities(record: dict[str, Any], other: dict[str, Any], algo: str
                          ) -> tuple[dict[str, Any], dict[str, Any]]:
    """The :func:`cell_identity` of learner ``algo`` under two settings records, with a
    by-variant ``values`` (the study's searched value of each variant it trains) cut to
    the variants both name: an invocation that trains fewer variants makes some of the
    same cells, not other ones, while one variant's value that differs makes other cells."""
    mine, theirs = cell_identity(record, algo), cell_identity(other, algo)
    if isinstance(mine.get("values"), dict) and isinstance(theirs.get("values"), dict):
        shared = mine["values"].keys() & theirs["values"].keys()
        mine["values"] = {k: v for k, v in mine["values"].items() if k in shared}
        theirs["values"] = {k: v for k, v in theirs["values"].items() if k in shared}
    return mine, theirs


def same_cells(record: dict[str, Any], other: dict[str, Any]) -> bool:
    """Whether two settings records make the same cells, for every learner (so that the
    invocation records of a narrower or wider invocation into a folder stay together)."""
    return all(mine == theirs for mine, theirs in (
        comparable_identities(record, other, algo) for algo in protocol.EXPERIMENT_ALGOS))


def joined_settings(record: dict[str, Any], other: dict[str, Any]) -> dict[str, Any]:
    """The settings of a folder after an invocation with settings ``record`` into one whose
    settings were ``other``: ``record``'s, with a by-variant ``values`` holding every variant
    either names (``record``'s value where both do; the cells of a variant it did not train
    are still there, made with ``other``'s)."""
    joined = dict(record)
    if isinstance(record.get("values"), dict) and isinstance(other.get("values"), dict):
        joined["values"] = {**other["values"], **record["values"]}
    return joined
