"""`geoavatar train --minutes M`: the number of steps of a new run, chosen from a time budget.

The steps are chosen before the run starts, so the schedule still scales with them (APS at half the
run, the densification window, opacity resets, the learning-rate decay), exactly as with --steps.

How: a short warm-up on a throwaway copy of the run. It opens the data, builds the seeded initial
state, times WARMUP_STEPS training steps at the initial Gaussian count (one Gaussian per face), splits
every Gaussian twice (4x the count, the children smaller as densification makes them) and times as
many steps again, and times one validation image and one checkpoint. The copy is then dropped; the
run itself starts from its own seeded initial state (`new_state` reseeds every generator), so its
result is the one `--steps N` gives for the chosen N: the warm-up changes nothing but N.

The step time grows with the Gaussian count as densification adds Gaussians. The model: the time of
a step is linear in the count (fitted to the two measurements), and the count grows linearly from the
initial one to GROWTH times it over the densification window (densify.start .. densify.stop), staying
there afterwards. GROWTH = 4.5: our CPU runs ended with 5-7x their initial count when densification ran to
the end (15k -> 76k in 1500 steps at 128 px, -> 101k-106k in 6000 steps at 256 px); since it stops at a third
of the run (#40), 3000 steps at 256 px end with 2.6-2.8x on the calm test videos and 4.5x on the expressive d3,
whose count is kept so that a budget rarely overruns (BENCHMARKS.md). The time left after the warm-up
(and the second opening of the data) pays for the steps, the validation images (every --val-every,
default 5 % of the run, and one at the end) and the checkpoints (every --ckpt-every, default 5 %, and
last + final at the end). It is an estimate: other load on the machine and a different growth of the
Gaussian count move the real end time.
"""

from __future__ import annotations

import io
import math
import time
from dataclasses import asdict, dataclass, replace
from typing import Iterable

import torch

from geoavatar.config import TrainConfig
from geoavatar.errors import OptionError
from geoavatar.train.options import CKPT_EVERY_FRACTION, VAL_EVERY_FRACTION, default_interval

GROWTH = 4.5  # expected Gaussian count at the end of densification / the initial count (see above)
GROWN = 4  # the warm-up times steps at this multiple of the initial count (two splits of every Gaussian)
WARMUP_STEPS = 3  # timed steps at each count (after one untimed step)
clock = time.perf_counter  # the warm-up's clock (tests replace it)


@dataclass
class BudgetPlan:
    """The step count chosen for a time budget and the measurements behind it (recorded in config.json)."""

    minutes: float
    steps: int
    gaussians: int  # initial count (one per face)
    seconds_per_step: float  # measured at the initial count
    seconds_per_step_grown: float  # measured at GROWN x the initial count
    mean_seconds_per_step: float  # over the whole run, by the growth model
    growth: float  # GROWTH
    validation_seconds: float  # one validation image
    checkpoint_seconds: float  # one checkpoint
    overhead_seconds: float  # validation images + checkpoints of the whole run
    warmup_seconds: float  # the warm-up itself (opening the data included)
    open_seconds: float  # opening the data (the run does it again)
    estimated_end: str  # local time, "%Y-%m-%d %H:%M:%S"

    def to_json(self) -> dict:
        return asdict(self)

    def summary(self) -> str:
        return (f"--minutes {self.minutes:g}: a step takes {self.seconds_per_step:.3g} s with {self.gaussians:,} "
                f"Gaussians and {self.seconds_per_step_grown:.3g} s with {GROWN}x as many (warm-up of "
                f"{self.warmup_seconds:.0f} s on a throwaway copy); expecting {self.growth:g}x the Gaussians by the "
                f"end of densification: {self.steps} steps, estimated end {self.estimated_end}")


def step_time(count_ratio: float, seconds_initial: float, seconds_grown: float) -> float:
    """Seconds per step at `count_ratio` x the initial Gaussian count (linear through the two measurements)."""
    slope = (seconds_grown - seconds_initial) / (GROWN - 1)
    return max(seconds_initial + slope * (count_ratio - 1.0), 0.0)


def mean_step_seconds(config: TrainConfig, seconds_initial: float, seconds_grown: float, growth: float = GROWTH) -> float:
    """Mean seconds per step over `config`'s run: the count is 1x before densify.start, grows linearly to
    `growth` x until densify.stop (or the end), and stays there."""
    steps = config.steps
    start = min(max(config.densify.start, 0), steps)
    stop = min(max(config.densify.stop, start), steps)
    if stop <= start:  # no densification
        return step_time(1.0, seconds_initial, seconds_grown)
    before = start / steps
    during = (stop - start) / steps
    after = 1.0 - before - during
    # the time is linear in the count, so the mean over a linear growth is the time at the mean count
    return (before * step_time(1.0, seconds_initial, seconds_grown)
            + during * step_time((1.0 + growth) / 2.0, seconds_initial, seconds_grown)
            + after * step_time(growth, seconds_initial, seconds_grown))


def overhead_seconds(steps: int, val_every: int | None, ckpt_every: int | None, validation: float,
                     checkpoint: float) -> float:
    """Validation images and checkpoints of a run of `steps` steps (the trainer's defaults: every 5 %)."""
    val = val_every or default_interval(steps, VAL_EVERY_FRACTION)
    ckpt = ckpt_every or default_interval(steps, CKPT_EVERY_FRACTION)
    return (steps // val + 1) * validation + (steps // ckpt + 2) * checkpoint


def steps_for_budget(
    seconds: float,
    base: TrainConfig,
    keep: Iterable[str],
    seconds_initial: float,
    seconds_grown: float,
    validation: float,
    checkpoint: float,
    val_every: int | None = None,
    ckpt_every: int | None = None,
    growth: float = GROWTH,
) -> tuple[int, float, float]:
    """(steps, mean seconds per step, overhead seconds): the largest step count whose predicted time fits
    `seconds` (a bisection: the schedule, hence the mean step time, and the number of checkpoints depend
    on the count; the predicted time grows with it). Steps is 0 when not even one step fits."""
    keep = tuple(keep)

    def predicted(steps: int) -> tuple[float, float]:
        mean = mean_step_seconds(base.scaled_to(steps, keep), seconds_initial, seconds_grown, growth)
        return mean, overhead_seconds(steps, val_every, ckpt_every, validation, checkpoint)

    def fits(steps: int) -> bool:
        mean, overhead = predicted(steps)
        return steps * mean + overhead <= seconds

    if not fits(1):
        return (0, *predicted(1))
    fastest = max(min(seconds_initial, seconds_grown), 1e-9)
    low, high = 1, int(seconds / fastest) + 2  # fits(low); not fits(high)
    while high - low > 1:
        middle = (low + high) // 2
        low, high = (middle, high) if fits(middle) else (low, middle)
    return (low, *predicted(low))


def plan_budget(options, base: TrainConfig, minutes: float, keep: Iterable[str] = ()) -> BudgetPlan:
    """Time a throwaway copy of the new run `options` (RunOptions) with the configuration `base` (the
    paper's schedule plus the user's overrides, before scaling; `keep`: its milestones not to scale) and
    choose the steps that fit `minutes`. OptionError when not even one step fits."""
    from geoavatar.avatar import densify as densify_ops
    from geoavatar.train import checkpoint, state as training_state, trainer

    keep = tuple(keep)
    started = clock()
    data = training_state.open_training_data(options, base)
    open_seconds = clock() - started
    # no densification and no APS during the warm-up: it times plain steps at two known counts
    warm = replace(base, aps_step=2**62, densify=replace(base.densify, stop=0))
    state = training_state.new_state(data, warm, options.seed)
    gaussians = state.avatar.num_gaussians

    def timed(first: int) -> float:
        trainer.train_step(data, state, warm, first, options.seed)  # untimed: first-call costs, caches
        times = []
        for step in range(first + 1, first + 1 + WARMUP_STEPS):
            before = clock()
            trainer.train_step(data, state, warm, step, options.seed)
            times.append(clock() - before)
        return sorted(times)[len(times) // 2]

    initial = timed(1)
    for _ in range(int(round(math.log2(GROWN)))):
        everyone = torch.ones(state.avatar.num_gaussians, dtype=torch.bool, device=data.device)
        state.avatar.binding = densify_ops.split_gaussians(
            state.avatar.params, [state.optimizers["gaussians"]], state.avatar.binding, everyone, state.stats,
            children=2, shrink=base.densify.split_shrink, generator=state.generator)
    grown = timed(2 + WARMUP_STEPS)
    before = clock()
    trainer.validation_image(data, state)
    validation = clock() - before
    before = clock()
    torch.save(checkpoint.state_payload(state, data, warm, options), io.BytesIO())
    checkpoint = clock() - before
    warmup = clock() - started
    del state, data

    left = minutes * 60.0 - warmup - open_seconds
    steps, mean, overhead = steps_for_budget(left, base, keep, initial, grown, validation, checkpoint,
                                             options.val_every, options.ckpt_every)
    if steps < 1:
        raise OptionError(f"--minutes {minutes:g} is too short: the warm-up took {warmup:.0f} s and one step with "
                          f"its validation image and checkpoints about {initial + validation + 3 * checkpoint:.1f} s "
                          "more; give more minutes or --steps")
    end = time.time() + open_seconds + steps * mean + overhead
    return BudgetPlan(
        minutes=float(minutes), steps=steps, gaussians=gaussians, seconds_per_step=initial,
        seconds_per_step_grown=grown, mean_seconds_per_step=mean, growth=GROWTH, validation_seconds=validation,
        checkpoint_seconds=checkpoint, overhead_seconds=overhead, warmup_seconds=warmup, open_seconds=open_seconds,
        estimated_end=time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(end)),
    )


__all__ = ["GROWN", "GROWTH", "WARMUP_STEPS", "BudgetPlan", "mean_step_seconds", "overhead_seconds", "plan_budget",
           "step_time", "steps_for_budget"]
