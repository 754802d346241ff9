"""Policies: the trained network (and its portable file) and the scripted baselines.

A policy maps observations ``(N, 13)`` (layout: ``mecanum_hil.envs.observation_layout(task)``)
to actions ``(N, 3)`` = ``(n [rpm], omega [deg/s], theta [deg])``; the environment's limiter and
``record``'s checks keep what is sent within the robot's limits. Every policy knows the robot
profile, the task and the control period it is meant for.

The policy file (``.npz``, read without pickle) is documented in ``docs/rl.md``: arrays
``params``, ``input_offset``, ``input_scale`` and a JSON string ``meta`` (format, network,
features, action map and limits, robot profile, task with its parameters, control period,
calibration as TOML, training record).
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..errors import ConfigError
from ..model import Calibration, RobotProfile
from ..model.calibration import calibration_to_toml
from .network import FEATURES, Architecture, feature_normalisation, forward, outputs_to_action

FORMAT = "mecanum-hil-policy"
FORMAT_VERSION = 1
#: Robot profile fields a policy is bound to (the name and everything the dynamics use).
ROBOT_FIELDS = ("name", "wheel_radius_m", "lx_plus_ly_m", "body_length_m", "body_width_m",
                "wheel_speed_max_rpm")


def task_name(task) -> str:
    """``"reach"`` or ``"dodge"`` for a task object."""
    from ..envs import DodgeTask

    return "dodge" if isinstance(task, DodgeTask) else "reach"


def task_to_dict(task) -> dict[str, Any]:
    """The task's parameters (its dataclass fields)."""
    return {k: (list(v) if isinstance(v, tuple) else v)
            for k, v in dataclasses.asdict(task).items()}


def task_from_dict(name: str, params: dict[str, Any]):
    """The task object back from :func:`task_to_dict`."""
    from ..envs.task import TASKS

    if name not in TASKS:
        raise ConfigError(f"unknown task {name!r} (known: {', '.join(TASKS)})")
    kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in params.items()}
    try:
        return TASKS[name](**kw)
    except TypeError as err:
        raise ConfigError(f"task {name!r}: bad parameters ({err})") from err


def robot_to_dict(robot: RobotProfile) -> dict[str, Any]:
    """The robot profile fields a policy is bound to, plus where it came from."""
    return {**{k: getattr(robot, k) for k in ROBOT_FIELDS}, "source": robot.source}


def check_robot(bound: dict[str, Any], robot: RobotProfile, what: str) -> None:
    """Refuse a robot profile other than the one a policy was made for (one line)."""
    for key in ROBOT_FIELDS:
        mine, theirs = bound[key], getattr(robot, key)
        same = mine == theirs if isinstance(mine, str) else math.isclose(mine, theirs,
                                                                         rel_tol=1e-9)
        if not same:
            raise ConfigError(
                f"{what} was trained for robot profile '{bound['name']}' ({key} = {mine}), "
                f"not '{robot.name}' ({key} = {theirs}): train one for this robot")


@dataclass(frozen=True)
class ScriptedPolicy:
    """The scripted baselines (no training).

    ``reach``: the go-to-pose P controller of ``examples/reach_target.py``: drive towards the
    target in the robot frame at ``150 rpm/m`` times the distance (capped at the wheel limit),
    turn at twice the heading error [deg/s]. ``dodge``: run at full speed across the line of
    attack, away from it, without turning.
    """

    robot: RobotProfile
    task: Any
    control_period_s: float = 0.02
    name: str = "scripted"

    def act(self, obs: np.ndarray) -> np.ndarray:
        """Actions ``(N, 3)`` for observations ``(N, 13)``."""
        obs = np.atleast_2d(obs)
        nmax = self.robot.wheel_speed_max_rpm
        if task_name(self.task) == "dodge":
            # the normal to the left of the strike is at the attacker's bearing in the theta
            # convention (0 right, 90 ahead)
            theta = np.where(obs[:, 10] >= 0, obs[:, 12], obs[:, 12] + 180.0)
            return np.column_stack([np.full(len(obs), nmax), np.zeros(len(obs)),
                                    (theta + 180.0) % 360.0 - 180.0])
        fwd, left, dphi = obs[:, 10], obs[:, 11], obs[:, 12]
        n = np.minimum(nmax, 150.0 * np.hypot(fwd, left))  # slows down over the last ~0.6 m
        theta = np.degrees(np.arctan2(fwd, -left))
        omega = np.clip(2.0 * dphi, -self.robot.omega_max_dps, self.robot.omega_max_dps)
        return np.column_stack([n, omega, theta])

    def describe(self) -> dict[str, Any]:
        """What the policy is, for summaries."""
        return {"policy": "scripted", "task": task_name(self.task)}

    def calibration(self) -> Calibration:
        """The model the policy assumes (the paper's: a scripted policy assumes nothing)."""
        from ..model import load_calibration

        return load_calibration("paper")


@dataclass(frozen=True)
class NetworkPolicy:
    """A trained network with everything needed to run it (what a policy file holds).

    Attributes
    ----------
    arch : Architecture
    params : ndarray, shape (n_params,)
        Flat parameters (:meth:`Architecture.shapes` order).
    features : tuple of str
        Input features (:data:`~mecanum_hil.policy.network.FEATURES`).
    input_offset, input_scale : ndarray
        Normalisation ``(feature - offset) / scale``.
    robot : RobotProfile
        The robot it was trained for (limits and geometry).
    task : ReachTask or DodgeTask
        The task, with its parameters.
    control_period_s : float
        How long each action is held [s].
    calibration_toml : str
        The calibration it was trained on, as its TOML file.
    calibration_source : str
    training : dict
        How it was trained (seed, evaluations, budget, randomisation, returns, ...).
    """

    arch: Architecture
    params: np.ndarray
    features: tuple[str, ...]
    input_offset: np.ndarray
    input_scale: np.ndarray
    robot: RobotProfile
    task: Any
    control_period_s: float
    calibration_toml: str = ""
    calibration_source: str = ""
    training: dict[str, Any] = field(default_factory=dict)
    name: str = "network"

    @classmethod
    def initial(cls, robot: RobotProfile, task, control_period_s: float,
                calibration: Calibration, hidden: tuple[int, ...] = (8,)) -> NetworkPolicy:
        """An untrained network (all parameters zero: it stands still) for ``task``."""
        names = FEATURES[task_name(task)]
        offset, scale = feature_normalisation(names, robot)
        arch = Architecture(len(names), tuple(hidden))
        return cls(arch, np.zeros(arch.n_params), names, offset, scale, robot, task,
                   float(control_period_s), calibration_to_toml(calibration),
                   calibration.source)

    def with_params(self, params: np.ndarray, **training: Any) -> NetworkPolicy:
        """A copy with other parameters (and training notes merged in)."""
        return dataclasses.replace(self, params=np.asarray(params, dtype=float).copy(),
                                   training={**self.training, **training})

    def inputs(self, obs: np.ndarray) -> np.ndarray:
        """Normalised features of observations ``(..., 13)``."""
        from ..envs import observation_layout
        from .network import task_features

        x = task_features(obs, self.features, observation_layout(self.task))
        return (x - self.input_offset) / self.input_scale

    def act_population(self, params: np.ndarray, obs: np.ndarray) -> np.ndarray:
        """Actions ``(P, M, 3)`` of P parameter vectors ``(P, n)`` on observations ``(P, M,
        13)``."""
        return outputs_to_action(forward(self.arch, params, self.inputs(obs)), self.robot)

    def act(self, obs: np.ndarray) -> np.ndarray:
        """Actions ``(N, 3)`` for observations ``(N, 13)``."""
        obs = np.atleast_2d(obs)
        return self.act_population(self.params[None], obs[None])[0]

    def describe(self) -> dict[str, Any]:
        """What the policy is, for summaries."""
        return {"policy": "network", "task": task_name(self.task),
                "calibration": self.calibration_source, "hidden": list(self.arch.hidden),
                "randomize": bool(self.training.get("randomize", False))}

    def calibration(self) -> Calibration:
        """The calibration the policy was trained on (from the TOML text it carries)."""
        import tempfile

        from ..model import load_calibration

        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / (Path(self.calibration_source).name or "calibration.toml")
            path = path.with_suffix(".toml")
            path.write_text(self.calibration_toml)
            return dataclasses.replace(load_calibration(path), source=self.calibration_source)

    # -- the file ------------------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Write the policy file (``.npz``, no pickled objects)."""
        from ..envs import observation_layout

        path = Path(path)
        meta = {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "tool_version": __version__,
            "network": {"kind": "mlp", "activation": "tanh", "output": "tanh",
                        "hidden": list(self.arch.hidden), "n_inputs": self.arch.n_inputs,
                        "n_outputs": self.arch.n_outputs, "skip": bool(self.arch.hidden),
                        "parameter_order": [[n, list(s)] for n, s in self.arch.shapes()]},
            "features": list(self.features),
            "observation_layout": [name for name, _ in observation_layout(self.task)],
            "action_map": "polar",
            "action_low": [0.0, -self.robot.omega_max_dps, -180.0],
            "action_high": [self.robot.wheel_speed_max_rpm, self.robot.omega_max_dps, 180.0],
            "robot": robot_to_dict(self.robot),
            "task": {"name": task_name(self.task), "parameters": task_to_dict(self.task)},
            "control_period_s": self.control_period_s,
            "calibration": {"source": self.calibration_source, "toml": self.calibration_toml},
            "training": self.training,
        }
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with path.open("wb") as fh:
                np.savez(fh, meta=np.array(json.dumps(meta)), params=self.params,
                         input_offset=self.input_offset, input_scale=self.input_scale)
        except OSError as err:
            raise ConfigError(f"{path}: cannot write the policy: {err.strerror or err}") from err
        return path


def load_policy(path: str | Path) -> NetworkPolicy:
    """Read a policy file written by :meth:`NetworkPolicy.save`.

    Raises
    ------
    ConfigError
        Missing, not a policy file, another format version, or inconsistent arrays.
    """
    import zipfile

    path = Path(path)
    _check_zip(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"][()]))
            params = np.asarray(z["params"], dtype=float)
            offset = np.asarray(z["input_offset"], dtype=float)
            scale = np.asarray(z["input_scale"], dtype=float)
    except FileNotFoundError as err:
        raise ConfigError(f"{path}: no such policy file") from err
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile,
            json.JSONDecodeError) as err:
        raise ConfigError(f"{path}: not a mecanum-hil policy file ({err})") from err
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ConfigError(f"{path}: not a mecanum-hil policy file")
    if meta.get("format_version") != FORMAT_VERSION:
        raise ConfigError(f"{path}: policy format version {meta.get('format_version')}, this "
                          f"tool reads {FORMAT_VERSION}")
    try:
        net = meta["network"]
        arch = Architecture(int(net["n_inputs"]), tuple(int(h) for h in net["hidden"]),
                            int(net["n_outputs"]))
        rob = meta["robot"]
        robot = RobotProfile(**{k: rob[k] for k in ROBOT_FIELDS}, source=rob["source"])
        task = task_from_dict(meta["task"]["name"], meta["task"]["parameters"])
        features = tuple(meta["features"])
        period = float(meta["control_period_s"])
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        raise ConfigError(f"{path}: policy file lacks or garbles {err}") from err
    except ConfigError as err:  # the task's parameters
        raise ConfigError(f"{path}: task: {err}") from err
    _check_values(path, meta, robot, period)
    if params.shape != (arch.n_params,) or offset.shape != (arch.n_inputs,) \
            or scale.shape != (arch.n_inputs,) or len(features) != arch.n_inputs:
        raise ConfigError(f"{path}: policy arrays do not match its network")
    if not np.isfinite(params).all():
        bad = int(np.size(params) - np.isfinite(params).sum())
        raise ConfigError(f"{path}: {bad} of the network's {params.size} weights are not "
                          "finite (NaN or infinite): a training that diverged?")
    if not np.isfinite(offset).all():
        raise ConfigError(f"{path}: input_offset must be finite")
    if not (np.isfinite(scale).all() and (scale > 0).all()):
        raise ConfigError(f"{path}: input_scale must be finite and > 0")
    if features != FEATURES[task_name(task)]:
        raise ConfigError(f"{path}: features {features} are not those of the task")
    return NetworkPolicy(arch, params, features, offset, scale, robot, task, period,
                         meta["calibration"].get("toml", ""),
                         meta["calibration"].get("source", ""), dict(meta.get("training", {})),
                         name=path.stem)


#: The longest control period a policy file may give [s].
MAX_CONTROL_PERIOD_S = 1.0


def _check_zip(path: Path) -> None:
    """One line for a file that cannot be a policy file (an ``.npz`` is a zip archive): numpy
    would take anything else for a pickle, or abort on an empty file."""
    try:
        with path.open("rb") as fh:
            head = fh.read(4)
    except FileNotFoundError as err:
        raise ConfigError(f"{path}: no such policy file") from err
    except OSError as err:
        raise ConfigError(f"{path}: cannot read the policy file: {err.strerror or err}") from err
    if not head.startswith(b"PK"):
        raise ConfigError(f"{path}: not a mecanum-hil policy file (.npz): "
                          + ("the file is empty" if not head else "not a zip archive"))


def _check_values(path: Path, meta: dict[str, Any], robot: RobotProfile, period: float) -> None:
    """Every number of the file finite and in range, the network one this tool computes: one
    line naming the file and the key."""
    net = meta["network"]
    for key, known in (("kind", "mlp"), ("activation", "tanh"), ("output", "tanh")):
        if net.get(key, known) != known:
            raise ConfigError(f"{path}: network.{key} {net.get(key)!r} is not supported "
                              f"(this tool computes {known!r})")
    if meta.get("action_map", "polar") != "polar":
        raise ConfigError(f"{path}: action_map {meta.get('action_map')!r} is not supported "
                          "(polar)")
    for key in ROBOT_FIELDS[1:]:
        v = getattr(robot, key)
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) \
                or v <= 0:
            raise ConfigError(f"{path}: robot.{key} must be a finite number > 0, got {v!r}")
    if not (math.isfinite(period) and 0 < period <= MAX_CONTROL_PERIOD_S):
        raise ConfigError(f"{path}: control_period_s must be > 0 and at most "
                          f"{MAX_CONTROL_PERIOD_S:g} s, got {period!r}")
    bounds = {}
    for key in ("action_low", "action_high"):
        if key not in meta:
            continue
        try:
            bounds[key] = np.asarray(meta[key], dtype=float)
        except (TypeError, ValueError):
            bounds[key] = np.full(1, np.nan)
        if bounds[key].shape != (3,) or not np.isfinite(bounds[key]).all():
            raise ConfigError(f"{path}: {key} must be three finite numbers, got {meta[key]!r}")
    if len(bounds) == 2 and not (bounds["action_low"] < bounds["action_high"]).all():
        raise ConfigError(f"{path}: action_low must be below action_high")


def resolve_policy(spec: str | Path, robot: RobotProfile, task: str | None = None,
                   control_period_s: float = 0.02):
    """A policy by name (``scripted``) or file, checked against ``robot`` and ``task``.

    Raises
    ------
    ConfigError
        (One line.) The file was trained for another robot profile or another task.
    """
    from ..envs.task import resolve_task

    if str(spec) == "scripted":
        return ScriptedPolicy(robot, resolve_task(task or "reach"), control_period_s)
    policy = load_policy(spec)
    check_robot(robot_to_dict(policy.robot), robot, f"policy {spec}")
    if task is not None and task != task_name(policy.task):
        raise ConfigError(f"policy {spec} was trained for task '{task_name(policy.task)}', not "
                          f"'{task}'")
    return policy
