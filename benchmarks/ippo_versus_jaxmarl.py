"""ccrjax's IPPO against JaxMARL's, training steps per second in one run.

    python benchmarks/ippo_versus_jaxmarl.py --jaxmarl-ippo PATH/baselines/IPPO/ippo_ff_mpe.py
    make bench-peers JAXMARL_IPPO=PATH/baselines/IPPO/ippo_ff_mpe.py

JaxMARL's IPPO (``baselines/IPPO/ippo_ff_mpe.py`` from a checkout of its repository; the
pip package has no baselines) runs in its own virtual environment
(``benchmarks/.peer-venv``, ``make bench-peers`` makes it) through
``benchmarks/jaxmarl_peer.py --ippo``, on its MPE ``simple_spread`` with 5 agents; ccrjax's
IPPO runs here, on ``nominal`` (the hazard-free task, like ``simple_spread``) and on the
hidden obstacle, with its continuous actions (the default) and with ``box9`` (discrete, as
JaxMARL's). Matched: the training environments per seed (ccrjax's default, 160), rollouts
of one 25-step episode, 5 robots, 4 epochs of 4 minibatches (5,000 robot-steps each),
64-64 tanh actor and critic, one seed and three in one vmapped program (JaxMARL's
program vmapped over 5 or more seeds compiled, then deadlocked on a 2-core CPU with jax
0.10.2, in the batched QR of its orthogonal initialisation; 3 ran). Not matched, and said
in the table: JaxMARL's networks see no robot index (ccrjax's shared ones get a one-hot), it
anneals its learning rate and adds an entropy bonus (arithmetic of a few scalars per
update), and logs through an ``io_callback`` after every update (a host round trip per
update that ccrjax's program does not make).

Each side times whole training iterations (rollout, advantages, update epochs) after a
compile and warm-up call, the median of ``--repeats`` calls of ``--updates`` iterations;
the peer first, then ccrjax, for each seed count. The ratio is ccrjax's environment steps
per second over JaxMARL's at the same seed count.
"""

from __future__ import annotations

import json
import platform
import subprocess
import sys
from pathlib import Path
from typing import Any

import jax

from ccrjax import cli
from ccrjax.agents.ppo import PPOConfig
from ccrjax.run.folder import git_commit
from ccrjax.training import TrainConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from train_throughput import measure  # noqa: E402 - a sibling script, not a package

PEER = Path(__file__).resolve().parent / "jaxmarl_peer.py"
PEER_PYTHON = Path(__file__).resolve().parent / ".peer-venv" / "bin" / "python"
SCENARIOS = ("nominal", "hidden_obstacle")
ACTIONS = {"continuous": None, "box9": PPOConfig(discrete=True)}


def peer_rows(python: Path, ippo_file: Path, envs: int, seeds: int, updates: int,
              repeats: int) -> list[dict[str, Any]]:
    """JaxMARL's IPPO timed by ``jaxmarl_peer.py --ippo`` in its own interpreter."""
    command = [str(python), str(PEER), "--ippo", str(ippo_file), "--ippo-envs", str(envs),
               "--ippo-seeds", str(seeds), "--updates", str(updates),
               "--repeats", str(repeats), "--json"]
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode:
        raise SystemExit(f"ippo_versus_jaxmarl.py: the peer failed ({' '.join(command)}):\n"
                         + done.stderr.strip()[-2000:])
    return [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]


def main(argv: list[str] | None = None) -> int:
    parser = cli.Parser(prog="python benchmarks/ippo_versus_jaxmarl.py",
                        description=__doc__.split("\n")[0])
    parser.add_argument("--jaxmarl-ippo", type=Path, required=True, metavar="FILE",
                        help="JaxMARL's baselines/IPPO/ippo_ff_mpe.py")
    parser.add_argument("--peer-python", type=Path, default=PEER_PYTHON,
                        help="the peer's interpreter (default: benchmarks/.peer-venv's)")
    parser.add_argument("--seeds", nargs="+", type=cli.int_in(1, 1024), default=[1, 3],
                        help="seeds trained at once, one program each (default: 1 3; "
                        "JaxMARL's program vmapped over 5 or more seeds deadlocks on a 2-core "
                        "CPU with jax 0.10.2, in its initialisation's batched QR)")
    parser.add_argument("--updates", type=cli.positive_int, default=20,
                        help="training iterations per timed call (default: %(default)s)")
    parser.add_argument("--repeats", type=cli.positive_int, default=5,
                        help="timed calls; the median is reported (default: %(default)s)")
    parser.add_argument("--json", action="store_true", help="one JSON object per line")
    args = parser.parse_args(argv)
    for name, path in (("--jaxmarl-ippo", args.jaxmarl_ippo),
                       ("--peer-python", args.peer_python)):
        if not path.is_file():
            cli.fail(parser.prog, f"{name} must be a file, got {str(path)!r}"
                     + (" (make bench-peers makes it)" if name == "--peer-python" else ""))
    envs = TrainConfig(algo="ippo").num_envs

    table = []
    for seeds in args.seeds:
        theirs = peer_rows(args.peer_python, args.jaxmarl_ippo, envs, seeds, args.updates,
                           args.repeats)[0]
        table.append(theirs)
        for scenario in SCENARIOS:
            for actions, learner in ACTIONS.items():
                ours = measure("ippo", ["plain"], scenario, args.updates, args.repeats, seeds,
                               learner)[0]
                ours.update(actions=actions, learner="ccrjax_ippo",
                            ratio_to_jaxmarl=ours["env_steps_per_s"]
                            / theirs["env_steps_per_s"])
                table.append(ours)
    if args.json:
        for row in table:
            print(json.dumps(row))
        return 0
    print(f"{platform.node()} · {jax.devices()[0].device_kind} · jax {jax.__version__} · "
          f"commit {git_commit()[:12]}")
    print(f"IPPO training, {envs} environments x 25 steps per rollout, 5 robots, 4 epochs x 4 "
          f"minibatches; median of {args.repeats} calls of {args.updates} iterations")
    header = (f"{'program':14} {'task':24} {'actions':10} {'seeds':>5} "
              f"{'env steps/s':>12} {'all seeds':>12} {'x JaxMARL':>9}")
    print(header)
    print("-" * len(header))
    for row in table:
        ratio = row.get("ratio_to_jaxmarl")
        print(f"{row['learner']:14} {row['scenario']:24} {row.get('actions', 'discrete 5'):10} "
              f"{row['seeds']:>5} {row['env_steps_per_s']:12,.0f} "
              f"{row['env_steps_per_s_all_seeds']:12,.0f} "
              f"{'' if ratio is None else f'{ratio:.1f}':>9}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
