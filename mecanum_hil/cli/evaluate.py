"""``mecanum-hil evaluate``: a policy's success rate, return, time to target or margin, in
simulation."""


from typing import Annotated

import typer

from ._options import CalibrationOpt, JsonOpt, RobotOpt


def command(
    policy: Annotated[str, typer.Argument(
        help="Policy file (.npz) from train, or 'scripted' (the go-to-pose / run-across "
        "baseline).", metavar="POLICY")],
    calibration: CalibrationOpt = "paper",
    robot: RobotOpt = "tdam-stm",
    task: Annotated[str | None, typer.Option(
        "--task", help="reach or dodge (default: the policy's; scripted: reach).")] = None,
    episodes: Annotated[int, typer.Option("--episodes", min=1, help="Episodes.")] = 256,
    seed: Annotated[int, typer.Option(
        "--seed", min=0, help="Episode i draws its target or strike from seed + i.")] = 0,
    randomize: Annotated[bool, typer.Option(
        "--randomize", help="Draw A, B, C within the calibration's intervals per episode.")
    ] = False,
    json_out: JsonOpt = False,
) -> None:
    """Evaluate a policy on a calibration's model (every effect simulated)."""
    import json

    from ..model import load_calibration, load_robot_profile
    from ..policy import evaluate, resolve_policy

    rob = load_robot_profile(robot)
    pol = resolve_policy(policy, rob, task)
    cal = load_calibration(calibration)
    ev = evaluate(pol, cal, rob, episodes=episodes, seed=seed, randomize=randomize)
    doc = {**ev.as_dict(), "policy": policy, "calibration": cal.source, "seed": seed,
           "control_period_s": pol.control_period_s}
    if json_out:
        typer.echo(json.dumps(doc))
        return
    typer.echo(f"{policy} on {cal.source} ({ev.task}, {ev.episodes} episodes, seed {seed}):")
    typer.echo(f"  success     {100 * ev.success_rate:.1f} % ({int(ev.success.sum())} of "
               f"{ev.episodes})")
    typer.echo(f"  mean return {ev.mean_return:+.3f}")
    if ev.task == "reach":
        typer.echo(f"  time to target {ev.time_to_target_s:.2f} s (mean over successes)")
    else:
        typer.echo(f"  margin at the deadline {ev.margin_m:+.3f} m (mean; > 0 clear)")
