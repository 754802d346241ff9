"""``mecanum-hil train``: train a policy on a calibration's model (CMA-ES, the ``rl`` extra)."""


from pathlib import Path
from typing import Annotated

import typer

from ._options import CalibrationOpt, JsonOpt, RobotOpt


def command(
    out: Annotated[Path, typer.Option("--out", "-o", help="Policy file (.npz) to write.",
                                      metavar="POLICY")],
    calibration: CalibrationOpt = "paper",
    robot: RobotOpt = "tdam-stm",
    task: Annotated[str, typer.Option("--task", help="reach or dodge.")] = "reach",
    budget_s: Annotated[float, typer.Option(
        "--budget-s", help="Wall-time budget of the training [s].")] = 300.0,
    generations: Annotated[int | None, typer.Option(
        "--generations", min=1, help="Stop after this many CMA-ES generations (reproducible: "
        "with --seed the same policy every time).")] = None,
    seed: Annotated[int, typer.Option("--seed", min=0, help="Seed of the search and the "
                                                            "episodes, at most 4294967294.")] = 0,
    randomize: Annotated[bool, typer.Option(
        "--randomize", help="Draw A, B, C within the calibration's 95 % intervals at every "
        "episode.")] = False,
    episodes: Annotated[int, typer.Option(
        "--episodes", min=1, help="Episodes per candidate per generation, at most 4096.")] = 48,
    hidden: Annotated[int, typer.Option(
        "--hidden", min=0, help="Hidden tanh units (0: a linear policy), at most 128 (CMA-ES "
        "keeps a full covariance of the ~15 x HIDDEN parameters).")] = 8,
    control_period_s: Annotated[float, typer.Option(
        "--control-period", help="How long each action is held [s].")] = 0.02,
    progress: Annotated[bool, typer.Option(
        "--progress/--no-progress", help="Show a progress bar.")] = True,
    json_out: JsonOpt = False,
) -> None:
    """Train a policy on a calibration's vectorised model (every effect simulated)."""
    import json

    from ..envs.task import resolve_task
    from ..errors import ConfigError
    from ..model import load_calibration, load_robot_profile
    from ..policy import NetworkPolicy
    from ..policy.train import MAX_HIDDEN, check_training, train
    from ._options import refuse_overwriting, shipped_or_file

    if not control_period_s > 0:
        raise ConfigError(f"--control-period must be > 0 s, got {control_period_s}")
    if hidden > MAX_HIDDEN:
        raise ConfigError(f"--hidden must be within 0..{MAX_HIDDEN} units, got {hidden} (CMA-ES "
                          "keeps a full covariance matrix of all the network's parameters)")
    check_training(0, episodes, seed)
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
