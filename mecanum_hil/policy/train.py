"""Training a policy network by evolution strategies (CMA-ES, ``cma``) on the vector env.

Each generation CMA-ES proposes ``popsize`` parameter vectors; all of them run the *same*
``episodes`` episodes (common random numbers: the comparison between candidates is not blurred
by their drawing different targets) in one :class:`~mecanum_hil.envs.MecanumHILVectorEnv` of
``popsize * episodes`` robots, every effect of the calibration simulated, and the mean episode
return is each candidate's fitness. At the end the distribution's mean and the best candidate
seen are compared on a fresh validation set and the better one is kept.

Why ES and not deep RL: the tasks are low-dimensional (11 inputs, 3 outputs), episodes are
short, and the compiled vector environment steps thousands of robots per call, so a
gradient-free search over ~150 parameters is cheap, needs no value function, no replay buffer,
no tuning of learning rates, and installs as one pure-Python package (``pycma``).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..model import Calibration
from .evaluate import rollout
from .policies import NetworkPolicy

#: Widest hidden layer ``train --hidden`` builds: 128 tanh units are ~2000 parameters.
MAX_HIDDEN = 128
#: Most network parameters trained: CMA-ES keeps a full n x n covariance matrix (16 TiB for the
#: 1.5 million parameters of 100000 hidden units) and decomposes it at a cost of n^3.
MAX_PARAMS = 2500
#: Most episodes per candidate per generation: each generation runs ``popsize * episodes``
#: robots at once in one vector environment.
MAX_EPISODES = 4096
#: Largest seed (CMA-ES is seeded with ``seed + 1``, NumPy takes up to 2**32 - 1).
MAX_SEED = 2 ** 32 - 2


def check_training(n_params: int, episodes: int, seed: int) -> None:
    """Refuse a training too big to allocate, or a seed the generators refuse, before anything
    is allocated.

    Parameters
    ----------
    n_params : int
        Parameters of the network, at most :data:`MAX_PARAMS`.
    episodes : int
        Episodes per candidate per generation, 1 .. :data:`MAX_EPISODES`.
    seed : int
        0 .. :data:`MAX_SEED`.

    Raises
    ------
    ConfigError
        One line naming the bound.
    """
    if n_params > MAX_PARAMS:
        raise ConfigError(f"the network has {n_params} parameters; CMA-ES trains at most "
                          f"{MAX_PARAMS} (a full covariance of n x n; --hidden at most "
                          f"{MAX_HIDDEN})")
    if not 1 <= episodes <= MAX_EPISODES:
        raise ConfigError(f"--episodes must be within 1..{MAX_EPISODES}, got {episodes}")
    if not 0 <= seed <= MAX_SEED:
        raise ConfigError(f"--seed must be within 0..{MAX_SEED}, got {seed}")


@dataclass(frozen=True)
class TrainResult:
    """A trained policy and how the training went.

    Attributes
    ----------
    policy : NetworkPolicy
    generations, evaluations : int
        CMA-ES generations; candidate evaluations (episodes run: ``evaluations * episodes``).
    best_return, mean_return : float
        Last generation's best and mean candidate fitness (mean episode return).
    validation_return : float
        Mean return of the kept parameters on the validation episodes.
    history : ndarray, shape (generations, 2)
        Best and mean fitness of every generation.
    elapsed_s : float
        Wall time [s].
    """

    policy: NetworkPolicy
    generations: int
    evaluations: int
    best_return: float
    mean_return: float
    validation_return: float
    history: np.ndarray
    elapsed_s: float


def train(policy: NetworkPolicy, calibration: Calibration | str, *, budget_s: float = 300.0,
          generations: int | None = None, episodes: int = 24, popsize: int | None = None,
          sigma0: float = 0.5, seed: int = 0, randomize: bool = False,
          validation_episodes: int = 256,
          progress: Callable[[int, float, float, float], None] | None = None) -> TrainResult:
    """Train ``policy``'s network on ``calibration``'s model by CMA-ES.

    Parameters
    ----------
    policy : NetworkPolicy
        Gives the architecture (at most :data:`MAX_PARAMS` parameters), task, robot and
        control period (its parameters start the search).
    calibration : Calibration or str
        The model trained on (every effect simulated).
    budget_s : float
        Wall-time budget [s]; the last generation that fits is the last one run.
    generations : int, optional
        Stop after this many generations (whichever comes first; reproducible runs use it).
    episodes : int
        Episodes per candidate per generation (at most :data:`MAX_EPISODES`).
    popsize : int, optional
        Candidates per generation (default: CMA-ES's ``4 + 3 ln(n)``).
    sigma0 : float
        Initial step size of the search.
    seed : int
        Seeds CMA-ES and the episodes' draws: the same seed and ``generations`` give the same
        policy.
    randomize : bool
        Draw A, B, C within the calibration's intervals at every episode.
    validation_episodes : int
        Episodes on which the final choice is made.
    progress : callable, optional
        ``progress(evaluations, elapsed_s, best, mean)`` after every generation.
    """
    if not budget_s > 0 or (generations is not None and generations < 1) or episodes < 1:
        raise ConfigError("need a positive budget, at least one generation and one episode")
    check_training(policy.params.size, episodes, seed)
    es = _evolution_strategy(policy, sigma0, seed, popsize)
    P = es.popsize
    envs = _vector_env(policy, calibration, P * episodes, randomize)
    rng = np.random.default_rng(seed)
    t0 = time.monotonic()
    history, best_x = _search(es, envs, policy, rng, episodes, generations, budget_s, t0,
                              progress)
    # the best candidate's score is biased upwards (it won on these episodes); the mean of the
    # search distribution is often better: decide on episodes neither has seen
    finalists = np.array([es.result.xfavorite, best_x])
    val = _validation_returns(policy, calibration, finalists, validation_episodes, randomize,
                              rng)
    k = int(np.argmax(val))
    hist = np.array(history)
    elapsed = time.monotonic() - t0
    trained = policy.with_params(
        finalists[k], method="cma-es", seed=int(seed), generations=len(history),
        evaluations=len(history) * P, popsize=P, episodes_per_candidate=episodes,
        sigma0=sigma0, randomize=bool(randomize), budget_s=float(budget_s),
        elapsed_s=round(elapsed, 2), validation_return=float(val[k]),
        kept="mean" if k == 0 else "best")
    return TrainResult(trained, len(history), len(history) * P, float(hist[-1, 0]),
                       float(hist[-1, 1]), float(val[k]), hist, elapsed)


def _evolution_strategy(policy: NetworkPolicy, sigma0: float, seed: int, popsize: int | None):
    """CMA-ES started at ``policy``'s parameters with step size ``sigma0``, seeded by
    ``seed``."""
    try:
        import cma
    except ImportError as err:
        raise ConfigError("training needs the rl extra: pip install 'mecanum-hil[rl]'") from err
    opts = {"seed": int(seed) + 1, "verbose": -9, "CMA_diagonal": False}
    if popsize is not None:
        opts["popsize"] = int(popsize)
    return cma.CMAEvolutionStrategy(policy.params.copy(), sigma0, opts)


def _vector_env(policy: NetworkPolicy, calibration: Calibration | str, n_envs: int,
                randomize: bool):
    """``n_envs`` episodes at once of ``policy``'s task on ``calibration``'s model."""
    from ..envs import MecanumHILVectorEnv

    return MecanumHILVectorEnv(n_envs, calibration, policy.robot,
                               control_period_s=policy.control_period_s, task=policy.task,
                               randomize=randomize)


def _search(es, envs, policy: NetworkPolicy, rng: np.random.Generator, episodes: int,
            generations: int | None, budget_s: float, t0: float,
            progress: Callable[[int, float, float, float], None] | None):
    """Run CMA-ES generations until ``generations`` or the budget ``budget_s`` [s] from
    ``t0`` [s, monotonic] is reached (the last one that fits is the last one run).

    Returns the (best, mean) return of each generation and the best candidate seen.
    """
    P = es.popsize
    history: list[tuple[float, float]] = []
    best_f, best_x = -np.inf, policy.params.copy()
    gen_s = 0.0
    while generations is None or len(history) < generations:
        elapsed = time.monotonic() - t0
        if history and elapsed + 1.5 * gen_s > budget_s:
            break
        g0 = time.monotonic()
        X, returns = _generation(es, envs, policy, rng, episodes)
        i = int(np.argmax(returns))
        if returns[i] > best_f:
            best_f, best_x = float(returns[i]), X[i].copy()
        history.append((float(returns.max()), float(returns.mean())))
        gen_s = time.monotonic() - g0
        if progress is not None:
            progress(len(history) * P, time.monotonic() - t0, *history[-1])
    return history, best_x


def _generation(es, envs, policy: NetworkPolicy, rng: np.random.Generator, episodes: int):
    """One CMA-ES generation: its candidates (P, n) and their mean returns (P,) over
    ``episodes`` episodes each, told to ``es``."""
    P = es.popsize
    X = np.asarray(es.ask())
    base = int(rng.integers(1 << 30))
    seeds = [base + m for _ in range(P) for m in range(episodes)]

    def act(obs, X=X):
        return policy.act_population(X, obs.reshape(P, episodes, -1)).reshape(-1, 3)

    returns = rollout(envs, act, seeds)[0].reshape(P, episodes).mean(axis=1)
    es.tell(list(X), list(-returns))
    return X, returns


def _validation_returns(policy: NetworkPolicy, calibration: Calibration | str,
                        finalists: np.ndarray, validation_episodes: int, randomize: bool,
                        rng: np.random.Generator) -> np.ndarray:
    """The mean return of each of the ``finalists`` (F, n) on ``validation_episodes`` fresh
    episodes, shape (F,)."""
    n = len(finalists)
    venvs = _vector_env(policy, calibration, n * validation_episodes, randomize)
    base = int(rng.integers(1 << 30))
    seeds = [base + m for _ in range(n) for m in range(validation_episodes)]
    val = rollout(venvs, lambda obs: policy.act_population(
        finalists, obs.reshape(n, validation_episodes, -1)).reshape(-1, 3), seeds)[0]
    return val.reshape(n, validation_episodes).mean(axis=1)
