"""DAgger's settings (DaggerConfig), apart from dagger.py, which imports torch: the reproduce config reads them."""

from __future__ import annotations

from dataclasses import dataclass, field

from crchfl_sumo.core.numbers import MAX_DRIVE_S, check_range
from crchfl_sumo.driving.drive import DriveConfig
from crchfl_sumo.driving.drive_bench import STUCK_S
from crchfl_sumo.driving.drive_bench_tasks import task_by_name
from crchfl_sumo.driving.policies import RoutePolicyConfig
from crchfl_sumo.learning.settings import CLASS_WEIGHTINGS

# A learner standing within this of a stop line it must stop at is labelled to hold: the data set's
# drivers never creep towards a red light, so a creep label there is one the data never gave.
HOLD_SHORT_M = 10.0


# Fine-tuning a tenth as fast as the recipe trains: at the recipe's 1e-3, three epochs left one of
# three models off the road, depending on the order of the samples alone (docs/model.md).
FINE_TUNE_LEARNING_RATE = 1e-4
# The fine-tuning's steer class weights: "start" keeps the start model's (learning.settings.TrainConfig). The
# labels are corrections, nearly all of them steer classes other than straight, and the start's sqrt_inverse
# weights raised them further: a strong start model then left the route in T junctions it crossed straight
# (docs/measurements.md, 2026-12-06, eighth).
KEEP_START_WEIGHTING = "start"
FINE_TUNE_CLASS_WEIGHTINGS = (KEEP_START_WEIGHTING, *CLASS_WEIGHTINGS)
FINE_TUNE_CLASS_WEIGHTING = "none"
MAX_ITERATIONS = 100


@dataclass(frozen=True)
class DaggerConfig:
    """Settings of one round of expert-labelled drives.

    tasks     drive-bench suites the routes are drawn from
    episodes  drives per task and town: 30 drove the traffic suite 11 points better than 10 on three seeds
              (docs/measurements.md, 2026-12-06, eighth)
    seed      draws the routes (not the benchmark's seed)
    every     one labelled sample every this many steps
    max_s     a drive ends after this long (or when stuck for STUCK_S, as in drive-bench)
    corrections_only  keep only the states where the expert steps in (is_correction): measured,
              all states taught the models to run red lights (docs/model.md)
    expert    the route expert that labels (RoutePolicyConfig); it holds where the learner stood
              still short of a red light instead of creeping up to the line
    """

    tasks: tuple[str, ...] = ("navigation_traffic",)
    episodes: int = 30
    seed: int = 1000
    every: int = 2
    max_s: float = 90.0
    corrections_only: bool = True
    drive: DriveConfig = field(default_factory=lambda: DriveConfig(stuck_s=STUCK_S))
    expert: RoutePolicyConfig = field(default_factory=lambda: RoutePolicyConfig(hold_short_m=HOLD_SHORT_M))

    def __post_init__(self) -> None:
        for name in self.tasks:
            task_by_name(name)
        check_range(self.episodes, "dagger.episodes", 1, 10_000, "a number of drives")
        check_range(self.every, "dagger.every", 1, 10_000, "a number of steps")
        check_range(self.max_s, "dagger.max_s", 0, MAX_DRIVE_S, "simulated seconds", lo_open=True)
