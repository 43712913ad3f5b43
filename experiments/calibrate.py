"""Calibration of the scenarios on reference controllers: ``python experiments/calibrate.py``.

    python experiments/calibrate.py                         # 1024 episodes per row
    python experiments/calibrate.py --episodes 64 --out /tmp/c   # small, for the tests
    python experiments/calibrate.py --regimes --out /tmp/r  # the information regimes

The paper publishes no sizes, only its plain learners' danger and success (Tables I
and II). ccrjax chooses the scenario parameters so that the hazard-blind go-to-goal
controller, which heads for the target as a plain learner does, lands in the paper's
plain regime, and so that the oracle, which knows the hazard and detours around it,
shows the task can be done safely. Only reference controllers enter this choice:
never CCR or the pessimistic baseline, whose results must not feed the environment's
design. The bands (from the paper's plain rows):

* turbulence: go-to-goal danger 40-55%, success >= 90%;
* strong wind: go-to-goal danger 20-35%, success 60-90%;
* hidden obstacle: go-to-goal danger >= 35%, success <= 40%;
* every scenario: oracle success >= 80%, danger <= 5%; gaming policies success <= 5%;
  the same with MAAC's discrete actions (``box9``).

It prints, and writes to ``<out>/calibration.md`` and ``calibration.json``:

1. every reference controller x scenario at the defaults (success, danger, final
   distance to the target, distance to the hazard centre, return), the paper's
   plain rows beside them, and whether each band holds;
2. the trade-off behind each default: the main size parameter of each scenario
   varied around its default, with the go-to-goal and oracle rows (a larger hazard
   raises the go-to-goal danger but lengthens the oracle's detour);
3. the discrete action sets (MAAC acts with discrete actions; the paper does not say
   which): every controller snapped to the nearest action of ``box9`` (``{-1, 0, 1}^2``,
   the set MAAC uses) and the go-to-goal and oracle snapped to the MPE's five (none, -x,
   +x, -y, +y), whose force lies in the unit L1 ball where the continuous force fills the
   box ``[-1, 1]^2``: the table that shows why MAAC uses ``box9``.

``--regimes`` measures instead what the team's information is worth, over a grid of the
hazard's placement and the team's formation (``experiments/regimes.py`` says what and
why), and writes ``<out>/regimes.md`` and ``regimes.json``.
"""

from __future__ import annotations

# ruff: noqa: E402 - the stop handling is installed before the other imports
from ccrjax import terminal

if __name__ == "__main__":  # a command: Ctrl-C and SIGTERM are answered from here on
    terminal.install("python experiments/calibrate.py")

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import jax

from ccrjax import cli
from ccrjax.envs.env import ROBOT_RADIUS, EmergencyEnv
from ccrjax.envs.world import DEFAULT_DISCRETE_ACTION_SET
from ccrjax.run.folder import git_commit, write_atomic
from experiments import regimes
from experiments.ledger import add_out_options, device_name, prepare_out
from experiments.paper import PAPER
from experiments.reference_controllers import CONTROLLERS, GAMING, evaluate_controller

PROG = "python experiments/calibrate.py"
SCENARIOS = ("turbulence", "strong_wind", "hidden_obstacle", "nominal")
METRICS = ("success_rate", "danger_frequency", "target_distance", "hazard_distance", "return")
# (go-to-goal danger low, high, go-to-goal success low, high) per scenario.
BANDS = {
    "turbulence": (0.40, 0.55, 0.90, 1.00),
    "strong_wind": (0.20, 0.35, 0.60, 0.90),
    "hidden_obstacle": (0.35, 1.00, 0.00, 0.40),
}
ORACLE_SUCCESS, ORACLE_DANGER, GAMING_SUCCESS = 0.80, 0.05, 0.05
# The trade-off tables: one parameter per scenario, varied around its default.
SWEEPS = {
    "turbulence": ("radius_range", [(0.6, 0.7), (0.75, 0.85), (0.9, 1.0)]),
    "strong_wind": ("force", [6.0, 8.0, 10.0, 12.0, 15.0]),
    "hidden_obstacle": ("length_range", [(0.6, 1.4), (1.0, 1.6), (1.2, 2.0), (1.6, 2.4)]),
}
PAPER_LEARNERS = {"iddpg": "DDPG", "maddpg": "MADDPG", "maac": "MAAC"}
# The discrete action sets measured, and the controllers measured with each: MAAC's set
# (box9) meets every band the continuous actions do; the MPE's five only shows its cost.
ACTION_SET_CONTROLLERS = {"box9": None, "mpe5": ("go_to_goal", "oracle")}  # None: all
REGIMES_SELECT = 128  # --regimes: selection episodes per memoriser height
REGIMES_MEASURED = "369 s"  # the full grid's time in --help (experiments/results/regimes)


def measure(scenario: str, controller: str, episodes: int, seed: int,
            params: dict[str, Any] | None = None, action_set: str | None = None
            ) -> dict[str, float]:
    """One controller's metrics over ``episodes`` episodes of one scenario, with continuous
    actions or snapped to the discrete ``action_set``."""
    env = EmergencyEnv(scenario, num_envs=episodes, scenario_params=params,
                 discrete_actions=action_set is not None,
                 discrete_action_set=action_set or DEFAULT_DISCRETE_ACTION_SET)
    metrics = jax.jit(lambda key: evaluate_controller(env, controller, key))(
        jax.random.PRNGKey(seed)
    )
    return {name: float(metrics[name]) for name in METRICS}


def measure_action_sets(episodes: int, seed: int) -> dict[str, dict[str, dict[str, Any]]]:
    """``{action set: {scenario: {controller: metrics}}}`` (:data:`ACTION_SET_CONTROLLERS`)."""
    return {
        action_set: {s: {c: measure(s, c, episodes, seed, action_set=action_set)
                         for c in (controllers or CONTROLLERS)} for s in SCENARIOS}
        for action_set, controllers in ACTION_SET_CONTROLLERS.items()
    }


def band_checks(rows: dict[str, dict[str, dict[str, float]]],
                action_sets: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """Each band of the module docstring, its measured value and whether it holds."""
    checks = []

    def check(what: str, value: float, low: float, high: float) -> None:
        checks.append({"check": what, "value": value, "low": low, "high": high,
                       "holds": bool(low <= value <= high)})

    for scenario, (d_low, d_high, s_low, s_high) in BANDS.items():
        blind = rows[scenario]["go_to_goal"]
        check(f"{scenario}: go-to-goal danger", blind["danger_frequency"], d_low, d_high)
        check(f"{scenario}: go-to-goal success", blind["success_rate"], s_low, s_high)
    for scenario in SCENARIOS:
        oracle = rows[scenario]["oracle"]
        check(f"{scenario}: oracle success", oracle["success_rate"], ORACLE_SUCCESS, 1.0)
        check(f"{scenario}: oracle danger", oracle["danger_frequency"], 0.0, ORACLE_DANGER)
        for gaming in GAMING:
            check(f"{scenario}: {gaming} success", rows[scenario][gaming]["success_rate"],
                  0.0, GAMING_SUCCESS)
    for scenario, box9 in ((action_sets or {}).get("box9") or {}).items():
        check(f"{scenario}, box9: oracle success", box9["oracle"]["success_rate"],
              ORACLE_SUCCESS, 1.0)
        check(f"{scenario}, box9: oracle danger", box9["oracle"]["danger_frequency"],
              0.0, ORACLE_DANGER)
        for gaming in GAMING:
            check(f"{scenario}, box9: {gaming} success", box9[gaming]["success_rate"],
                  0.0, GAMING_SUCCESS)
    return checks


def _pct(value: float) -> str:
    return f"{100 * value:.1f}%"


def markdown(result: dict[str, Any]) -> str:
    rows, lines = result["rows"], []
    lines += [
        "### Reference controllers x scenarios (defaults)", "",
        f"{result['episodes']} episodes of 5 robots per row, seed {result['seed']}; "
        "success: in the target area at the last step; danger: share of robot-steps in "
        "danger; distances at the last step (target) and averaged over steps (hazard centre).",
        "",
        "| scenario | controller | success | danger | final distance to target | "
        "distance to hazard centre | return |",
        "|---|---|---|---|---|---|---|",
    ]
    for scenario in SCENARIOS:
        for controller in CONTROLLERS:
            m = rows[scenario][controller]
            lines.append(
                f"| {scenario} | {controller} | {_pct(m['success_rate'])} | "
                f"{_pct(m['danger_frequency'])} | {m['target_distance']:.3f} | "
                f"{m['hazard_distance']:.3f} | {m['return']:.1f} |"
            )
    lines += ["", "The paper's plain learners (Tables I and II), for comparison:", "",
              "| scenario | learner | success | danger |", "|---|---|---|---|"]
    for scenario in BANDS:
        for algo, name in PAPER_LEARNERS.items():
            key = (scenario, algo, "plain")
            lines.append(f"| {scenario} | {name} | {_pct(PAPER['success_rate'][key])} | "
                         f"{_pct(PAPER['danger_frequency'][key])} |")
    lines += ["", "### Bands", "", "| check | value | band | holds |", "|---|---|---|---|"]
    for c in result["checks"]:
        lines.append(f"| {c['check']} | {_pct(c['value'])} | {_pct(c['low'])} to "
                     f"{_pct(c['high'])} | {'yes' if c['holds'] else '**no**'} |")
    lines += ["", "### Trade-offs around the defaults", "",
              "| scenario | parameter | value | go-to-goal success | go-to-goal danger | "
              "oracle success | oracle danger |", "|---|---|---|---|---|---|---|"]
    for entry in result["sweeps"]:
        blind, oracle = entry["go_to_goal"], entry["oracle"]
        lines.append(
            f"| {entry['scenario']} | {entry['parameter']} | {entry['value']} | "
            f"{_pct(blind['success_rate'])} | {_pct(blind['danger_frequency'])} | "
            f"{_pct(oracle['success_rate'])} | {_pct(oracle['danger_frequency'])} |"
        )
    if result.get("action_sets"):
        spaces = ["continuous", *result["action_sets"]]
        lines += ["", "### Discrete action sets (MAAC's actions)", "",
                  "Each controller's command snapped to the nearest action of the set; "
                  "success / danger / return.", "",
                  "| scenario | controller | " + " | ".join(spaces) + " |",
                  "|---|---|" + "---|" * len(spaces)]
        for scenario in SCENARIOS:
            for controller in CONTROLLERS:
                cells = [rows[scenario][controller]] + [
                    result["action_sets"][space][scenario].get(controller)
                    for space in spaces[1:]]
                lines.append(f"| {scenario} | {controller} | " + " | ".join(
                    "" if m is None else f"{_pct(m['success_rate'])} / "
                    f"{_pct(m['danger_frequency'])} / {m['return']:.1f}" for m in cells) + " |")
    lines += ["", f"Made by `{result['command']}` at commit `{result['commit']}` "
              f"in {result['seconds']:.0f} s."]
    return "\n".join(lines) + "\n"


def build_parser() -> argparse.ArgumentParser:
    parser = cli.Parser(
        prog=PROG,
        description="Reference controllers x scenarios: the table that justifies the "
                    "scenario defaults (about 3 minutes on a 2-core CPU).",
    )
    parser.add_argument("--episodes", type=cli.int_in(1, 65536), default=1024,
                        help="episodes (environments) per row (default 1024)")
    parser.add_argument("--seed", type=cli.seed_int, default=0, help="random seed (default 0)")
    parser.add_argument("--no-sweeps", action="store_true",
                        help="skip the trade-off tables around the defaults")
    parser.add_argument("--no-action-sets", action="store_true",
                        help="skip the discrete action sets' table and bands")
    regime = parser.add_argument_group(
        "information regimes (--regimes)",
        "hidden obstacle, turbulence, strong wind x hazard placement x formation: the five "
        "rows go_to_goal, self_reactive, team_informed, oracle, memoriser, go-to-goal's "
        "forewarned share and the 'informative' flag (experiments/regimes.py). The full grid "
        f"({len(regimes.REGIME_SCENARIOS) * len(regimes.PLACEMENTS) * len(regimes.FORMATIONS)} "
        f"regimes, 1024 episodes per row, {REGIMES_SELECT} selection episodes per "
        f"height) took {REGIMES_MEASURED} on a 2-core CPU.")
    regime.add_argument("--regimes", action="store_true",
                        help="measure the information regimes instead of the calibration")
    regime.add_argument("--selection-seed", type=cli.seed_int, default=1,
                        help="seed of the episodes that choose the memoriser's height; must "
                             "differ from --seed (default 1)")
    regime.add_argument("--select-episodes", type=cli.int_in(1, 65536),
                        default=REGIMES_SELECT,
                        help=f"episodes per height of that choice (default {REGIMES_SELECT})")
    regime.add_argument("--scenarios", nargs="+", choices=regimes.REGIME_SCENARIOS,
                        default=list(regimes.REGIME_SCENARIOS),
                        help="scenarios of the grid (default: all three)")
    regime.add_argument("--placements", nargs="+", type=cli.float_in(0.0),
                        default=list(regimes.PLACEMENTS),
                        help="half-ranges h of the hazard's height [-h, h] (default "
                             f"{' '.join(f'{h:g}' for h in regimes.PLACEMENTS)})")
    regime.add_argument("--spacings", nargs="+", type=cli.float_in(0.0),
                        default=[spacing or 0.0 for _, spacing in regimes.FORMATIONS],
                        help="formations: 0 for abreast, else a column with this spacing "
                             "(default "
                             f"{' '.join(f'{s or 0:g}' for _, s in regimes.FORMATIONS)})")
    add_out_options(parser, "calibration", Path("runs/calibration"))
    return parser


def main_regimes(args: argparse.Namespace, argv: list[str] | None) -> int:
    """``--regimes``: measures the grid and writes ``regimes.md`` and ``regimes.json``."""
    commit = git_commit()  # the code that measures is the code loaded now
    start = time.time()
    formations = [("abreast", None) if spacing == 0 else ("column", spacing)
                  for spacing in args.spacings]
    grid = regimes.measure_grid(
        args.episodes, args.seed, args.selection_seed, args.select_episodes,
        length_episodes=args.episodes, scenarios=tuple(args.scenarios),
        placements=tuple(args.placements), formations=formations,
        log=lambda line: print(line, file=sys.stderr, flush=True))
    result = {
        "episodes": args.episodes, "seed": args.seed, "selection_seed": args.selection_seed,
        "select_episodes": args.select_episodes, "grid": grid, "commit": commit,
        "device": device_name(), "command": " ".join([PROG, *(argv or sys.argv[1:])]),
        "seconds": time.time() - start,
    }
    text = regimes.markdown(result)
    write_atomic(args.out / "regimes.json", json.dumps(result, indent=1))
    write_atomic(args.out / "regimes.md", text)
    print(text)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.regimes and (args.no_sweeps or args.no_action_sets):
        cli.fail(PROG, "--no-sweeps and --no-action-sets apply to the calibration, not "
                       "to --regimes")
    if args.regimes and args.selection_seed == args.seed:
        cli.fail(PROG, f"--selection-seed must differ from --seed ({args.seed}): the "
                       "memoriser's height is chosen on other episodes than it is measured on")
    if args.regimes:
        for spacing in args.spacings:  # a formation no scenario could run: refused at once
            if spacing:
                try:
                    regimes.regime_layout(0.0, "column", spacing).check_team(
                        regimes.NUM_ROBOTS, ROBOT_RADIUS)
                except ValueError as error:
                    cli.fail(PROG, f"--spacings {spacing:g}: {error}")
    prepare_out(PROG, args.out, args.force)
    if args.regimes:
        return main_regimes(args, argv)
    commit = git_commit()  # the code that measures is the code loaded now
    start = time.time()
    rows = {s: {c: measure(s, c, args.episodes, args.seed) for c in CONTROLLERS}
            for s in SCENARIOS}
    sweeps = []
    if not args.no_sweeps:
        for scenario, (parameter, values) in SWEEPS.items():
            for value in values:
                params = {parameter: value}
                sweeps.append({
                    "scenario": scenario, "parameter": parameter, "value": value,
                    **{c: measure(scenario, c, args.episodes, args.seed, params)
                       for c in ("go_to_goal", "oracle")},
                })
    action_sets = {} if args.no_action_sets else measure_action_sets(args.episodes, args.seed)
    result = {
        "episodes": args.episodes, "seed": args.seed, "rows": rows, "sweeps": sweeps,
        "action_sets": action_sets, "checks": band_checks(rows, action_sets),
        "commit": commit,
        "command": " ".join([PROG, *(argv or sys.argv[1:])]),
        "seconds": time.time() - start,
    }
    text = markdown(result)
    write_atomic(args.out / "calibration.json", json.dumps(result, indent=1))
    write_atomic(args.out / "calibration.md", text)
    print(text)
    failed = [c["check"] for c in result["checks"] if not c["holds"]]
    print(f"{len(result['checks']) - len(failed)} of {len(result['checks'])} bands hold"
          + (f"; outside: {', '.join(failed)}" if failed else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(terminal.run_command(
        PROG, main,
        "nothing was written (the results are written when the measurement ends)"))
