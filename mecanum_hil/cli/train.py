"""``mecanum-hil train``: train a policy on a calibration's model (CMA-ES, the ``rl`` extra)."""


from pathlib import Path
from typing import Annotated

import typer

from ._options import CalibrationOpt, JsonOpt, ProgressOpt, RobotOpt

PolicyOutOpt = Annotated[Path, typer.Option("--out", "-o", help="Policy file (.npz) to write.",
                                             metavar="POLICY")]
TaskOpt = Annotated[str, typer.Option("--task", help="reach or dodge.")]
BudgetOpt = Annotated[float, typer.Option(
    "--budget-s", help="Wall-time budget of the training [s].")]
GenerationsOpt = Annotated[int | None, typer.Option(
    "--generations", min=1, help="Stop after this many CMA-ES generations (reproducible: "
    "with --seed the same policy every time).")]
SeedOpt = Annotated[int, typer.Option("--seed", min=0, help="Seed of the search and the "
                                                            "episodes, at most 4294967294.")]
RandomizeOpt = Annotated[bool, typer.Option(
    "--randomize", help="Draw A, B, C within the calibration's 95 % intervals at every "
    "episode.")]
EpisodesOpt = Annotated[int, typer.Option(
    "--episodes", min=1, help="Episodes per candidate per generation, at most 4096.")]
HiddenOpt = Annotated[int, typer.Option(
    "--hidden", min=0, help="Hidden tanh units (0: a linear policy), at most 128 (CMA-ES "
    "keeps a full covariance of the ~15 x HIDDEN parameters).")]
ControlPeriodOpt = Annotated[float, typer.Option(
    "--control-period", help="How long each action is held [s].")]


def command(
    out: PolicyOutOpt,
    calibration: CalibrationOpt = "paper",
    robot: RobotOpt = "tdam-stm",
    task: TaskOpt = "reach",
    budget_s: BudgetOpt = 300.0,
    generations: GenerationsOpt = None,
    seed: SeedOpt = 0,
    randomize: RandomizeOpt = False,
    episodes: EpisodesOpt = 48,
    hidden: HiddenOpt = 8,
    control_period_s: ControlPeriodOpt = 0.02,
    progress: ProgressOpt = True,
    json_out: JsonOpt = False,
) -> None:
    """Train a policy on a calibration's vectorised model (every effect simulated)."""
    import json

    from ..envs.task import resolve_task
    from ..model import load_calibration, load_robot_profile
    from ..policy import NetworkPolicy
    from ..policy.train import train
    from ._options import refuse_overwriting, shipped_or_file

    _check(control_period_s, hidden, episodes, seed)
    refuse_overwriting([(shipped_or_file(calibration), "the calibration"),
                        (shipped_or_file(robot), "the robot profile")], [(out, "--out")])
    cal = load_calibration(calibration)
    rob = load_robot_profile(robot)
    start = NetworkPolicy.initial(rob, resolve_task(task), control_period_s, cal,
                                  (hidden,) if hidden else ())
    kwargs = dict(budget_s=budget_s, generations=generations, seed=seed, randomize=randomize,
                  episodes=episodes)
    if progress and not json_out:
        result = _train_with_progress(start, cal, kwargs)
    else:
        result = train(start, cal, **kwargs)
    path = result.policy.save(out)
    doc = {"policy": str(path), "task": task, "calibration": cal.source, "robot": rob.name,
           "generations": result.generations, "evaluations": result.evaluations,
           "best_return": result.best_return, "mean_return": result.mean_return,
           "validation_return": result.validation_return, "elapsed_s": result.elapsed_s,
           "randomize": randomize, "seed": seed}
    if json_out:
        typer.echo(json.dumps(doc))
        return
    typer.echo(f"trained {result.generations} generations ({result.evaluations} evaluations) "
               f"in {result.elapsed_s:.1f} s; validation return {result.validation_return:+.3f}")
    typer.echo(f"wrote {path}")


def _check(control_period_s: float, hidden: int, episodes: int, seed: int) -> None:
    """One-line errors for a control period, network or training the search cannot run."""
    from ..errors import ConfigError
    from ..policy.train import MAX_HIDDEN, check_training

    if not control_period_s > 0:
        raise ConfigError(f"--control-period must be > 0 s, got {control_period_s}")
    if hidden > MAX_HIDDEN:
        raise ConfigError(f"--hidden must be within 0..{MAX_HIDDEN} units, got {hidden} (CMA-ES "
                          "keeps a full covariance matrix of all the network's parameters)")
    check_training(0, episodes, seed)


def _train_with_progress(start, cal, kwargs):
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from ..policy.train import train

    columns = (TextColumn("[bold]train[/]"), BarColumn(), TimeElapsedColumn(),
               TextColumn("{task.fields[counts]}"))
    with Progress(*columns, transient=True) as bar:
        budget = kwargs["budget_s"]
        task = bar.add_task("train", total=budget, counts="")

        def update(evaluations, elapsed_s, best, mean):
            bar.update(task, completed=min(elapsed_s, budget),
                       counts=f"evaluations {evaluations}  best {best:+.3f}  mean {mean:+.3f}")

        return train(start, cal, progress=update, **kwargs)
