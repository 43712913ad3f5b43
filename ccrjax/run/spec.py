"""A training run's specification: the per-seed configuration, the seeds, and how the
run is checkpointed. ``python -m ccrjax.train`` writes it into the run folder's
``config.json``; ``python -m ccrjax.evaluate`` and ``--resume`` read it back."""

from __future__ import annotations

import dataclasses
from typing import Any

from ccrjax.checks import check_int
from ccrjax.training import TrainConfig, config_from_dict, config_to_dict


@dataclasses.dataclass(frozen=True)
class RunSpec:
    """A training run: the per-seed configuration and how the run is driven."""

    train: TrainConfig
    seeds: int = 1  # number of seeds, trained at once in one program
    seed_offset: int = 0  # first seed: the seeds are offset, offset + 1, ..., offset + seeds - 1
    # environment steps per seed between checkpoints, rounded to whole evaluation intervals
    checkpoint_every: int = 100_000
    keep_checkpoints: int = 2  # how many of the latest checkpoints to keep

    def __post_init__(self) -> None:
        for name, low in (("seeds", 1), ("seed_offset", 0), ("checkpoint_every", 1),
                          ("keep_checkpoints", 1)):
            check_int("", name, getattr(self, name), low)
        if self.seed_offset + self.seeds > 2**31:
            raise ValueError("seed_offset + seeds must stay below 2**31")

    @property
    def seed_list(self) -> list[int]:
        return [self.seed_offset + k for k in range(self.seeds)]

    @property
    def chunks_per_checkpoint(self) -> int:
        return max(1, round(self.checkpoint_every / self.train.eval_every))

    def to_dict(self) -> dict[str, Any]:
        return {
            "seeds": self.seeds,
            "seed_offset": self.seed_offset,
            "checkpoint_every": self.checkpoint_every,
            "keep_checkpoints": self.keep_checkpoints,
            "train": config_to_dict(self.train),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> RunSpec:
        data = dict(data)
        return cls(train=config_from_dict(data.pop("train")), **data)
