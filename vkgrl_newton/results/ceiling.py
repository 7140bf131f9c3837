"""The measured ceiling of each task (issue 40): what the privileged scripted demonstrator, the privileged oracle
in the KGRL action space and the blind spiral search seat on the paired evaluation episodes, as
ceiling_table.csv beside this file transcribes docs/results/ceiling_40 (tools/ceiling.py made those). The
learning curves draw them beside the prior and the thesis's level (results.plots)."""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

__all__ = ["CeilingLevel", "CEILING_TABLE", "load_ceiling", "ceiling_levels"]

CEILING_TABLE = Path(__file__).with_name("ceiling_table.csv")


@dataclass(frozen=True)
class CeilingLevel:
    task: str
    env: str
    action_dim: int
    eval_seed: int
    num_envs: int
    controller: str  # scripted, oracle, search
    successes: int
    episodes: int
    source: str  # the JSON under docs/results/ceiling_40 it is transcribed from

    @property
    def rate(self) -> float:
        return self.successes / self.episodes


def load_ceiling(path: Path = CEILING_TABLE) -> list[CeilingLevel]:
    lines = [ln for ln in Path(path).read_text().splitlines() if ln and not ln.startswith("#")]
    return [CeilingLevel(r["task"], r["env"], int(r["action_dim"]), int(r["eval_seed"]), int(r["num_envs"]),
                         r["controller"], int(r["successes"]), int(r["episodes"]), r["source"])
            for r in csv.DictReader(lines)]


def ceiling_levels(task: str, env: str, action_dim: int, eval_seed: int, num_envs: int) -> list[CeilingLevel]:
    """The levels measured on these episodes (the same task, family, action space, eval seed and worlds);
    [] where none was measured."""
    return [c for c in load_ceiling() if (c.task, c.env, c.action_dim, c.eval_seed, c.num_envs)
            == (task, env, action_dim, eval_seed, num_envs)]
