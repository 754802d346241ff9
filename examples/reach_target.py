"""MecanumHIL-v0 in a loop: a scripted go-to-pose policy against a random one.

Runs 256 episodes of each policy in the vectorised environment (one numpy call per step for
all robots), prints the mean episode return and success rate, and plots the paths of a few
episodes of the single environment to a PNG. Nothing is trained; this shows the loop a
reinforcement-learning library would drive.

Run: ``python examples/reach_target.py [--calibration CAL.toml] [--out paths.png]``.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import gymnasium as gym
import numpy as np

import mecanum_hil.envs  # noqa: F401  (registers MecanumHIL-v0)
from mecanum_hil.envs import ReachTask
from mecanum_hil.model import RobotProfile
from mecanum_hil.policy import ScriptedPolicy


def scripted(obs: np.ndarray, n_max_rpm: float, omega_max_dps: float) -> np.ndarray:
    """Head for the target in the robot frame, turn towards its heading (a P controller).

    The package's baseline (``mecanum_hil.policy.ScriptedPolicy``, what ``mecanum-hil
    evaluate scripted`` runs) on a robot with these limits.

    Parameters
    ----------
    obs : ndarray, shape (N, 13)
        Observations (``mecanum_hil.envs.observation_layout()``).

    Returns
    -------
    ndarray, shape (N, 3)
        ``(n [rpm], omega [deg/s], theta [deg])``; the environment keeps them within limits.
    """
    robot = RobotProfile(wheel_speed_max_rpm=n_max_rpm)
    robot = replace(robot, lx_plus_ly_m=robot.wheel_radius_m * 6.0 * n_max_rpm / omega_max_dps)
    return ScriptedPolicy(robot, ReachTask()).act(obs)


def run_vector(policy: str, calibration: str, episodes: int, seed: int):
    """Episode returns and successes of ``episodes`` episodes, one per robot."""
    envs = gym.make_vec("MecanumHIL-v0", num_envs=episodes, calibration=calibration)
    space = envs.single_action_space
    rng = np.random.default_rng(seed)
    obs, _ = envs.reset(seed=seed)
    returns = np.zeros(episodes)
    done = np.zeros(episodes, dtype=bool)
    success = np.zeros(episodes, dtype=bool)
    while not done.all():
        if policy == "scripted":
            action = scripted(obs, space.high[0], space.high[1])
        else:
            action = rng.uniform(space.low, space.high, size=(episodes, 3))
        obs, reward, terminated, truncated, _ = envs.step(action)
        returns += np.where(done, 0.0, reward)
        success |= terminated & ~done & envs.unwrapped.core.success
        done |= terminated | truncated
    return returns, success


def paths(calibration: str, seeds, policy: str):
    """Pose sequences and targets of single-environment episodes."""
    env = gym.make("MecanumHIL-v0", calibration=calibration)
    space = env.action_space
    out = []
    for seed in seeds:
        obs, info = env.reset(seed=seed)
        space.seed(seed)
        poses = [info["pose"]]
        done = False
        while not done:
            if policy == "scripted":
                action = scripted(obs[None], space.high[0], space.high[1])[0]
            else:
                action = space.sample()
            obs, _, terminated, truncated, info = env.step(action)
            poses.append(info["pose"])
            done = terminated or truncated
        out.append((np.array(poses), info["task_state"]))
    return out


def plot(runs, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 6))
    for policy, style in (("scripted", "-"), ("random", ":")):
        for i, (poses, target) in enumerate(runs[policy]):
            color = f"C{i}"
            ax.plot(poses[:, 0], poses[:, 1], style, color=color,
                    label=policy if i == 0 else None)
            if policy == "scripted":
                ax.plot(*target[:2], "x", color=color, ms=10)
                phi = np.radians(target[2])
                ax.arrow(target[0], target[1], 0.2 * np.cos(phi), 0.2 * np.sin(phi),
                         color=color, width=0.01)
    ax.plot(0, 0, "ko", label="start (heading 90 deg)")
    ax.set_xlabel("X [m]")
    ax.set_ylabel("Y [m]")
    ax.set_aspect("equal")
    ax.legend(loc="best")
    ax.set_title("MecanumHIL-v0: paths to target poses (x, arrow = heading)")
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calibration", default="paper", help="calibration name or TOML file")
    parser.add_argument("--episodes", type=int, default=256)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="reach_target_paths.png", help="PNG of paths")
    args = parser.parse_args()
    for policy in ("scripted", "random"):
        returns, success = run_vector(policy, args.calibration, args.episodes, args.seed)
        print(f"{policy:8s}: mean return {returns.mean():+.3f} (std {returns.std():.3f}), "
              f"success {100 * success.mean():.0f} % of {args.episodes} episodes")
    seeds = range(args.seed, args.seed + 4)
    plot({p: paths(args.calibration, seeds, p) for p in ("scripted", "random")}, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
