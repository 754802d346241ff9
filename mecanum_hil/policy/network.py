"""A small policy network in numpy: task features in, a command out.

The network sees a fixed set of *features* of the environment's 13-value observation
(:func:`task_features`), each normalised as ``(value - offset) / scale``, and maps them through
``tanh`` hidden layers plus a linear skip connection to three outputs in ``[-1, 1]``
(:func:`forward`). The outputs become a command by the *polar* action map
(:func:`outputs_to_action`): ``(forward, left)`` is the direction and fraction of the top speed
to drive at, the third output the fraction of the top turning speed. The environment's limiter
(and ``record``'s checks) then keep every command within the robot's limits.

Everything is batched: a whole population of parameter vectors (``(P, n_params)``) is evaluated
on ``(P, M, n_features)`` inputs in one call, which is what evolution strategies need.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model import RobotProfile
from ..units import RPM_TO_RAD_S

#: Input features of each task: observation names; ``sin:``/``cos:`` of an angle observation
#: [deg], ``sin2:``/``cos2:`` of twice the angle.
FEATURES = {
    "reach": ("target_forward_m", "target_left_m", "sin:target_dphi_deg",
              "cos:target_dphi_deg", "vx_mps", "vy_mps", "omega_dps", "wheel1_rpm",
              "wheel2_rpm", "wheel3_rpm", "wheel4_rpm"),
    # the body's extent across the line of attack repeats every 180 deg of bearing: sin2/cos2
    # (of twice the angle) let the policy turn the narrow side to the line
    "dodge": ("line_offset_m", "time_to_strike_s", "sin:attacker_bearing_deg",
              "cos:attacker_bearing_deg", "sin2:attacker_bearing_deg",
              "cos2:attacker_bearing_deg", "vx_mps", "vy_mps", "omega_dps", "wheel1_rpm",
              "wheel2_rpm", "wheel3_rpm", "wheel4_rpm"),
}


def feature_normalisation(names, robot: RobotProfile) -> tuple[np.ndarray, np.ndarray]:
    """Offsets and scales of the features: physical ranges of the robot, not data statistics.

    Positions are divided by 1 m, times by 1 s, velocities by the top speed the wheel limit
    allows, wheel speeds by the wheel limit, so every input is of order one whatever robot.
    """
    v_max = robot.wheel_speed_max_rpm * RPM_TO_RAD_S * robot.wheel_radius_m
    scale = []
    for name in names:
        if name.startswith(("sin", "cos")) or name.endswith(("_m", "_s")):
            scale.append(1.0)
        elif name.endswith("_mps"):
            scale.append(v_max)
        elif name == "omega_dps":
            scale.append(robot.omega_max_dps)
        elif name.endswith("_rpm"):
            scale.append(robot.wheel_speed_max_rpm)
        else:
            raise ValueError(f"no normalisation for feature {name!r}")
    return np.zeros(len(names)), np.asarray(scale, dtype=float)


def task_features(obs: np.ndarray, names, layout) -> np.ndarray:
    """The features ``names`` of observations ``obs`` (..., 13) whose entries are ``layout``."""
    index = {name: i for i, (name, _) in enumerate(layout)}
    out = np.empty((*obs.shape[:-1], len(names)))
    for j, name in enumerate(names):
        kind, _, base = name.rpartition(":")
        value = obs[..., index[base]]
        if kind:
            factor = 2.0 if kind.endswith("2") else 1.0
            trig = np.sin if kind.startswith("sin") else np.cos
            value = trig(factor * np.radians(value))
        out[..., j] = value
    return out


@dataclass(frozen=True)
class Architecture:
    """Shape of the network.

    Attributes
    ----------
    n_inputs : int
        Number of features.
    hidden : tuple of int
        Widths of the ``tanh`` hidden layers.
    n_outputs : int
        Outputs (3: forward, left, turn).
    """

    n_inputs: int
    hidden: tuple[int, ...] = (8,)
    n_outputs: int = 3

    def shapes(self) -> list[tuple[str, tuple[int, ...]]]:
        """Names and shapes of the parameter arrays, in the order of the flat vector.

        ``w0, b0, w1, b1, ...`` for the hidden layers and the output layer (``w`` is
        ``(out, in)``), then (with hidden layers) ``skip`` ``(n_outputs, n_inputs)`` from the
        inputs to the outputs.
        """
        sizes = [self.n_inputs, *self.hidden, self.n_outputs]
        out = []
        for i in range(len(sizes) - 1):
            out.append((f"w{i}", (sizes[i + 1], sizes[i])))
            out.append((f"b{i}", (sizes[i + 1],)))
        if self.hidden:  # without hidden layers w0 is already the linear map
            out.append(("skip", (self.n_outputs, self.n_inputs)))
        return out

    @property
    def n_params(self) -> int:
        """Length of the flat parameter vector."""
        return sum(int(np.prod(s)) for _, s in self.shapes())

    def unflatten(self, flat: np.ndarray) -> dict[str, np.ndarray]:
        """Parameter arrays from flat vectors ``(..., n_params)`` (views, leading axes kept)."""
        flat = np.asarray(flat, dtype=float)
        lead = flat.shape[:-1]
        out, pos = {}, 0
        for name, shape in self.shapes():
            size = int(np.prod(shape))
            out[name] = flat[..., pos:pos + size].reshape(*lead, *shape)
            pos += size
        return out

    def flatten(self, params: dict[str, np.ndarray]) -> np.ndarray:
        """The flat vector of one parameter set."""
        return np.concatenate([np.asarray(params[name], dtype=float).ravel()
                               for name, _ in self.shapes()])


def forward(arch: Architecture, flat: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Network outputs in ``[-1, 1]``.

    Parameters
    ----------
    flat : ndarray, shape (P, n_params)
        P parameter vectors.
    x : ndarray, shape (P, M, n_inputs)
        Normalised features, M per parameter vector.

    Returns
    -------
    ndarray, shape (P, M, n_outputs)
    """
    p = arch.unflatten(flat)
    layers = len(arch.hidden) + 1
    h = x
    for i in range(layers):
        h = np.einsum("pmi,poi->pmo", h, p[f"w{i}"]) + p[f"b{i}"][:, None, :]
        if i < layers - 1:
            h = np.tanh(h)
    if "skip" in p:
        h = h + np.einsum("pmi,poi->pmo", x, p["skip"])
    return np.tanh(h)


def outputs_to_action(out: np.ndarray, robot: RobotProfile) -> np.ndarray:
    """The polar action map: outputs ``(..., 3)`` in ``[-1, 1]`` to ``(n, omega, theta)``.

    ``n = min(1, |(forward, left)|) * wheel_speed_max_rpm`` [rpm], ``theta`` the direction of
    ``(forward, left)`` in the command convention (0 right, 90 ahead) [deg], ``omega = turn^3
    * omega_max_dps`` [deg/s]. The environment then scales ``n`` and ``omega`` together to the
    wheel limit where both are large. The cube gives a small turning output almost no turning:
    any turning takes wheel speed from the translation, and a search cannot set a weight to
    exactly zero.
    """
    fwd, left, turn = out[..., 0], out[..., 1], out[..., 2]
    n = np.minimum(1.0, np.hypot(fwd, left)) * robot.wheel_speed_max_rpm
    theta = np.degrees(np.arctan2(fwd, -left))
    return np.stack([n, turn ** 3 * robot.omega_max_dps, theta], axis=-1)
