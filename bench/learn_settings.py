"""Settings of `swimm bench learn` (bench.learn), apart from it so that `swimm bench --help` stays light."""

from __future__ import annotations

from dataclasses import dataclass, field

from learner_service.learn_settings import SmoothSettings
from services.settings import FilePath

SUMMARY = "summary.json"  # a results folder's summary, which --merge reads back (bench.learn_merge)


@dataclass
class LearnBenchSettings:
    """Flags of `swimm bench learn`."""

    algos: list[str] = field(default_factory=lambda: ["sac", "ppo", "td3"])  # named algorithms (hyperparams/*.yaml)
    seeds: list[int] = field(default_factory=lambda: [97, 101, 103])  # the SPEC's first training seeds
    budget_steps: int = 300_000  # env steps per run at most
    budget_min: float = 45.0  # wall minutes per run at most (the learner's training; start-up excluded)
    eval_every: int = 10_000  # env steps between evaluations during training
    eval_episodes: int = 2  # deterministic episodes per evaluation during training
    eval_max_steps: int = 3000  # steps of an evaluation episode (the SPEC's: no early termination)
    final_episodes: int = 20  # deterministic episodes of each run's final model
    final_seed: int = 127  # base seed of those episodes (the training evaluations use 113)
    thresholds: list[float] = field(default_factory=lambda: [2000.0, 2400.0])  # returns to time ("minutes_to")
    out: str = "runs/bench-learn"  # the results folder
    resume: bool = True  # skip runs that already finished in ``out``
    encoder_checkpoint: FilePath = ""  # the CMVAE (default: the shipped one)
    smooth: SmoothSettings = field(default_factory=SmoothSettings)  # flags --smooth-*: CAPS action smoothness
    actor_average: int = 0  # evaluate and keep the actor's weights averaged over ~N updates (swimm learn's flag)
    hyperparams: str = ""  # YAML mapping or file over each algorithm's shipped values: "{learning_rate: lin_7.3e-4}"
    merge: list[str] = field(default_factory=list)  # summary.json files to combine into --out instead of training

    def check(self) -> None:
        self.smooth.check()
        if not self.algos or not self.seeds:
            raise ValueError("bench learn needs at least one algorithm (--algos) and one seed (--seeds)")
        if len(set(self.seeds)) != len(self.seeds) or len(set(self.algos)) != len(self.algos):
            raise ValueError(f"--algos and --seeds must not repeat: got {self.algos} and {self.seeds}")
        if min(self.budget_steps, self.eval_every, self.eval_episodes, self.eval_max_steps, self.final_episodes) < 1:
            raise ValueError("budget_steps, eval_every, eval_episodes, eval_max_steps and final_episodes must be >= 1")
        if self.budget_min <= 0:
            raise ValueError(f"--budget-min must be > 0 minutes, got {self.budget_min}")


@dataclass(frozen=True)
class Layout:
    """How each run is served: training envs (the same gradient steps per env step whatever the number) and the
    sims they are split between (`swimm up --envs --sims`), from `swimm bench`'s ``--envs`` and ``--sims``."""

    envs: int = 1
    sims: int = 1

    def check(self) -> None:
        if self.envs < 1 or self.sims < 1 or self.envs % self.sims:
            raise ValueError(f"--envs must be >= 1 and --sims divide it, got {self.envs} envs and {self.sims} sims")


ONE_ENV = Layout()  # one env on one sim: the default layout
