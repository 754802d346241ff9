"""``mecanum-hil record --policy``: a trained (or the scripted) policy drives the robot.

Called by :mod:`mecanum_hil.cli.record` when ``--policy`` is given; the library side is
:mod:`mecanum_hil.link.policy_session`. ``--out`` is then a folder: one recording per episode
and ``summary.json``.
"""


from pathlib import Path

import typer

from ._options import echo_safely, link_name, raise_signal_end


def record_policy(*, out: Path, transport: str, port, interface, channel, bitrate, link_option,
                  robot: str, policy: str, task: str | None, episodes: int, seed: int,
                  connect_timeout_s: float, link_timeout_s: float, progress: bool,
                  shadow: str | None, on_divergence: str, json_out: bool, profile, commands,
                  dry_run: bool, foxglove=None, before_run=None, ros2=None) -> None:
    """Run ``episodes`` episodes of ``policy`` on the robot (see ``record --help``)."""
    from ..link.session import SessionConfig
    from ..link.transport import open_transport, transport_options
    from ..model import load_robot_profile
    from ..policy import resolve_policy

    _check(profile, commands, dry_run, foxglove, episodes, seed, shadow, on_divergence)
    rob = load_robot_profile(robot)
    pol = resolve_policy(policy, rob, task)  # refuses another robot's or task's policy
    cal = pol.calibration()  # its slip efficiencies turn wheel speeds into odometry

    options = transport_options(transport, port=port, interface=interface, channel=channel,
                                bitrate=bitrate, link_options=link_option)
    options.update(ros2 or {})
    where = link_name(transport, port, interface, channel, (ros2 or {}).get("cmd_topic", ""))
    make_observers, close_observers = _shadow_observers(shadow, on_divergence, rob)
    link = open_transport(transport, options)
    try:
        if before_run is not None:
            before_run()  # everything checked and the port open: the run starts here
        config = SessionConfig(connect_timeout_s=connect_timeout_s, link_timeout_s=link_timeout_s)
        meta = {"policy": str(policy), "policy_info": pol.describe()}
        kwargs = dict(episodes=episodes, seed=seed, out_dir=out, config=config,
                      make_observers=make_observers, close_observers=close_observers,
                      metadata=meta, echo=None if json_out else echo_safely)
        run = _run(link, pol, rob, cal, where, kwargs, progress and not json_out)
    finally:
        link.close()
    _end(run, out, episodes, json_out)


def _check(profile, commands, dry_run: bool, foxglove, episodes: int, seed: int,
           shadow: str | None, on_divergence: str) -> None:
    """One-line errors for options that do not go with ``--policy``."""
    from ..errors import ConfigError

    if profile is not None or commands is not None:
        raise ConfigError("--policy makes the commands itself: give no --profile or --commands")
    if dry_run:
        raise ConfigError("--dry-run checks a fixed command stream; a policy's commands depend "
                          "on the robot (try it with sim-robot, or `mecanum-hil evaluate`)")
    if foxglove is not None:
        raise ConfigError("--foxglove is not available with --policy yet")
    if episodes < 1 or seed < 0:
        raise ConfigError("--episodes must be >= 1 and --seed >= 0")
    if shadow is None and on_divergence != "none":
        raise ConfigError("--on-divergence acts on shadow mode's alarms: give --shadow CAL too "
                          "(without it nothing watches the run)")


def _shadow_observers(shadow: str | None, on_divergence: str, rob):
    """``(make_observers, close_observers)`` of shadow mode for each episode (``None, None``
    without ``--shadow``)."""
    if shadow is None:
        return None, None
    from ..model import load_calibration
    from ..monitor.core import ShadowConfig
    from ..monitor.eventlog import event_log_path
    from ..monitor.live import LiveShadow

    shadow_cal = load_calibration(shadow)
    closed: list[str] = []

    def make_observers(csv: Path):
        return [LiveShadow(shadow_cal, rob, ShadowConfig(), event_log_path(csv),
                           stop_on_divergence=on_divergence == "stop", echo=echo_safely,
                           header={"mode": "record --policy", "recording": str(csv),
                                   "on_divergence": on_divergence})]

    def close_observers(observers):
        for obs in observers:
            closed.append(obs.close())
            echo_safely(closed[-1])

    return make_observers, close_observers


def _run(link, pol, rob, cal, where: str, kwargs: dict, with_bar: bool):
    """The episodes, behind a progress bar where asked for."""
    from ..link.policy_session import run_policy_episodes

    if with_bar:
        return _run_with_progress(link, pol, rob, cal, where, kwargs)
    return run_policy_episodes(link, pol, rob, cal, **kwargs)


def _end(run, out: Path, episodes: int, json_out: bool) -> None:
    """Print the summary (a line, or JSON); end with the run's exit code (an error or a
    signal as such)."""
    import json

    s = run.summary
    if json_out:
        echo_safely(json.dumps(s))
    else:
        echo_safely(f"{s['end_reason']} (exit {s['exit_code']}): {s['episodes']} of {episodes} "
                    f"episodes, success {100 * s['success_rate']:.1f} %, mean return "
                    f"{s['mean_return']:+.3f}; wrote {Path(out) / 'summary.json'}")
    if run.exit_code == 0:
        return
    last = run.results[-1]
    if last.error is not None and last.reason not in ("interrupted", "terminated",
                                                      "observer_stop"):
        raise last.error
    raise_signal_end(s["end_reason"])
    raise typer.Exit(run.exit_code)


def _run_with_progress(link, pol, rob, cal, where, kwargs):
    from rich.progress import BarColumn, Progress, TextColumn

    from ..link.policy_session import run_policy_episodes

    columns = (TextColumn("[bold]record --policy[/] {task.description}"), BarColumn(),
               TextColumn("episode {task.fields[episode]}/{task.total:.0f}"),
               TextColumn("{task.fields[counts]}"))
    with Progress(*columns, transient=True) as bar:
        task = bar.add_task(where, total=kwargs["episodes"], episode=1, counts="")

        def update(i, elapsed_s, total_s, counts):
            bar.update(task, completed=i + min(elapsed_s / total_s, 1.0) if total_s else i,
                       episode=i + 1,
                       counts=f"{elapsed_s:.1f} s  sent {counts['sent']} rx {counts['received']} "
                              f"lost {counts['lost']}")

        return run_policy_episodes(link, pol, rob, cal, progress=update, **kwargs)
