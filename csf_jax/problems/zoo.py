"""Models beyond the paper's table: the benchmark of unseen models (``python -m experiments.zoo``).

Nine classic filtering problems, each small enough for a near-exact reference (a bootstrap
particle filter with 10^5 particles for d <= 4; the Kalman filter for the linear one):

* ``pendulum``: the README's example, a pendulum seen through its angle.
* ``lorenz63_gaps``: Lorenz-63 seen through x with noise variance 1; the benchmark removes 30% of
  the observation times (``ZOO_GAPS``).
* ``bearings``: a constant-velocity target in the plane seen by two bearing sensors (0.02 rad).
* ``folding``: a 3-D rotation seen through ``sin`` of two coordinates: each observation has many
  preimages.
* ``ungm``: the univariate nonstationary growth model of Gordon, Salmond & Smith (1993) with its
  time forcing ``8 cos(1.2 k)``: a time-varying model with a bimodal (``x^2 / 20``) sensor.
* ``stochastic_volatility``: an AR(1) log-variance seen through ``y = exp(x / 2) eps``, a
  non-additive likelihood.
* ``poisson_counts``: two coupled log-intensities seen through Poisson counts.
* ``lotka_volterra``: predators and prey in log-populations, the prey counted (Poisson): an
  exponential drift, the predators never seen.
* ``linear20``: a linear-Gaussian model in d = 20 observed at every other coordinate.

Three models of moderate dimension where nonlinearity meets dimension (the particle filter's
weights collapse, the EnKF's linear update is biased), chosen before any CSF setting was measured
on them; no near-exact reference exists for them, so their benchmark compares against the truth:

* ``well_chain``: a ring of 16 double wells coupled to their neighbours, the odd sites seen through
  ``x^3``: which well an unobserved site sits in is told only by its neighbours.
* ``lorenz96_abs``: Lorenz-96 with d = 40 and process noise, ``|x|`` seen at every other site: each
  observation has two preimages, resolved only through the dynamics.
* ``lorenz96_square``: Lorenz-96 with d = 20 and process noise, ``x^2 / 4`` seen at every other
  site.

Each is a frozen config (defaults = the benchmark's) and a cached builder, looked up through
``csf_jax.problems.get``.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from csf_jax import _checks
from csf_jax.problems.linear import linear_gaussian, to_model
from csf_jax.problems.lorenz96 import Lorenz96Config, attractor_point, rk4, rk4_step
from csf_jax.ssm import (
    StateSpaceModel,
    gaussian_noise,
    gaussian_process_noise,
    poisson_likelihood,
    volatility_likelihood,
)


def _gaussian_start(mean, std):
    """``initial_truth`` and ``initial_ensemble`` drawing ``N(mean, diag(std)^2)``."""
    mean = np.asarray(mean, np.float32)
    std = np.broadcast_to(np.asarray(std, np.float32), mean.shape).copy()

    def truth(key):
        return jnp.asarray(mean) + jnp.asarray(std) * jax.random.normal(key, mean.shape)

    def ensemble(key, n):
        return jnp.asarray(mean) + jnp.asarray(std) * jax.random.normal(key, (n,) + mean.shape)

    return truth, ensemble


def _numbers(config, field: str, shape: tuple, positive: bool = False) -> None:
    """Refuse a tuple field that is not finite numbers of ``shape`` (positive ones if asked)."""
    value = getattr(config, field)
    try:
        arr = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.shape != shape or not np.isfinite(arr).all() \
            or (positive and not (arr > 0).all()):
        what = "positive" if positive else "finite"
        raise ValueError(f"{type(config).__name__}.{field} must hold {what} numbers of shape "
                         f"{shape}, got {value!r}")


@dataclasses.dataclass(frozen=True)
class PendulumConfig:
    """The README's pendulum: ``x = (angle, rate)``, explicit Euler step ``dt``, angle observed."""

    dt: float = 0.1
    process_std: float = 0.1
    obs_std: float = 0.1
    num_steps: int = 50

    def __post_init__(self):
        _checks.check_fields(self, positive=("dt", "obs_std", "num_steps"),
                             nonnegative=("process_std",))


@functools.cache
def pendulum(c: PendulumConfig = PendulumConfig()) -> StateSpaceModel:
    def drift(x):
        return jnp.stack([x[0] + c.dt * x[1], x[1] - c.dt * jnp.sin(x[0])])

    truth, ensemble = _gaussian_start([1.0, 0.0], 0.1)
    return StateSpaceModel("pendulum", 2, 1, c.num_steps, c.dt, drift, lambda x: x[:1],
                           c.process_std, gaussian_noise(c.obs_std), truth, ensemble)


@dataclasses.dataclass(frozen=True)
class Lorenz63Config:
    """Lorenz-63 (10, 28, 8/3), ``substeps`` RK4 steps of ``dt`` per filter step, x observed."""

    dt: float = 0.01
    substeps: int = 5
    process_std: float = 0.1
    obs_std: float = 1.0
    init_std: float = 2.0
    num_steps: int = 200

    def __post_init__(self):
        _checks.check_fields(self, positive=("dt", "substeps", "obs_std", "init_std", "num_steps"),
                             nonnegative=("process_std",))


def lorenz63_tendency(x):
    return jnp.stack([10.0 * (x[1] - x[0]), x[0] * (28.0 - x[2]) - x[1],
                      x[0] * x[1] - 8.0 / 3.0 * x[2]])


@functools.cache
def lorenz63(c: Lorenz63Config = Lorenz63Config()) -> StateSpaceModel:
    def drift(x):
        return jax.lax.fori_loop(0, c.substeps, lambda i, x: rk4(lorenz63_tendency, x, c.dt), x)

    with jax.ensure_compile_time_eval():
        on = np.asarray(jax.lax.fori_loop(0, 2000, lambda i, x: rk4(lorenz63_tendency, x, c.dt),
                                          jnp.ones(3)))
    truth, ensemble = _gaussian_start(on, c.init_std)
    return StateSpaceModel("lorenz63_gaps", 3, 1, c.num_steps, c.dt * c.substeps, drift,
                           lambda x: x[:1], c.process_std, gaussian_noise(c.obs_std), truth,
                           ensemble)


@dataclasses.dataclass(frozen=True)
class BearingsConfig:
    """A constant-velocity target ``(px, py, vx, vy)`` and two bearing sensors below its path."""

    dt: float = 1.0
    position_std: float = 0.02
    velocity_std: float = 0.01
    obs_std: float = 0.02
    sensors: tuple = ((-15.0, -10.0), (15.0, -10.0))
    start: tuple = (-3.0, 5.0, 0.15, 0.05)
    start_std: tuple = (1.0, 1.0, 0.05, 0.05)
    num_steps: int = 60

    def __post_init__(self):
        _checks.check_fields(self, positive=("dt", "position_std", "velocity_std", "obs_std",
                                             "num_steps"))
        _numbers(self, "sensors", (len(self.sensors), 2))
        if not self.sensors:
            raise ValueError("BearingsConfig.sensors must hold at least one (x, y) sensor")
        _numbers(self, "start", (4,))
        _numbers(self, "start_std", (4,), positive=True)


@functools.cache
def bearings(c: BearingsConfig = BearingsConfig()) -> StateSpaceModel:
    F = np.array([[1, 0, c.dt, 0], [0, 1, 0, c.dt], [0, 0, 1, 0], [0, 0, 0, 1]], np.float32)
    sensors = np.asarray(c.sensors, np.float32)

    def drift(x):
        return jnp.asarray(F, x.dtype) @ x

    def observe(x):
        rel = x[None, :2] - jnp.asarray(sensors, x.dtype)
        return jnp.arctan2(rel[:, 1], rel[:, 0])

    q = np.diag([c.position_std, c.position_std, c.velocity_std, c.velocity_std]) ** 2
    truth, ensemble = _gaussian_start(c.start, c.start_std)
    return StateSpaceModel("bearings", 4, len(c.sensors), c.num_steps, c.dt, drift, observe,
                           c.position_std, gaussian_noise(c.obs_std), truth, ensemble,
                           process_noise=gaussian_process_noise(q))


@dataclasses.dataclass(frozen=True)
class FoldingConfig:
    """A rotation by ``angle`` about the axis (1, 1, 1) in 3-D, observed through
    ``sin(x_0), sin(x_1)``: each observation has many preimages."""

    angle: float = 0.2
    process_std: float = 0.05
    obs_std: float = 0.05
    start: tuple = (2.0, 1.0, -1.0)
    start_std: float = 0.5
    num_steps: int = 100

    def __post_init__(self):
        _checks.check_fields(self, positive=("obs_std", "start_std", "num_steps"),
                             nonnegative=("process_std",))
        _numbers(self, "start", (3,))


def _axis_rotation(angle: float) -> np.ndarray:
    """Rotation by ``angle`` about the unit axis (1, 1, 1) / sqrt(3) (Rodrigues)."""
    k = np.ones(3) / np.sqrt(3.0)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


@functools.cache
def folding(c: FoldingConfig = FoldingConfig()) -> StateSpaceModel:
    R = _axis_rotation(c.angle).astype(np.float32)

    def drift(x):
        return jnp.asarray(R, x.dtype) @ x

    truth, ensemble = _gaussian_start(c.start, c.start_std)
    return StateSpaceModel("folding", 3, 2, c.num_steps, 1.0, drift, lambda x: jnp.sin(x[:2]),
                           c.process_std, gaussian_noise(c.obs_std), truth, ensemble)


@dataclasses.dataclass(frozen=True)
class UNGMConfig:
    """``x_k = x/2 + 25 x / (1 + x^2) + forcing cos(1.2 k) + v_k``, ``y_k = x_k^2 / 20 + w_k``."""

    forcing: float = 8.0
    process_var: float = 10.0
    obs_var: float = 1.0
    init_var: float = 5.0
    num_steps: int = 100

    def __post_init__(self):
        _checks.check_fields(self, positive=("obs_var", "init_var", "num_steps"),
                             nonnegative=("process_var",))


@functools.cache
def ungm(c: UNGMConfig = UNGMConfig()) -> StateSpaceModel:
    def drift(x, step):
        k = jnp.asarray(step.k, x.dtype)
        return 0.5 * x + 25.0 * x / (1.0 + x * x) + c.forcing * jnp.cos(1.2 * k)

    def observe(x, step):
        return x * x / 20.0

    truth, ensemble = _gaussian_start([0.0], np.sqrt(c.init_var))
    return StateSpaceModel("ungm", 1, 1, c.num_steps, 1.0, drift, observe,
                           float(np.sqrt(c.process_var)), gaussian_noise(float(np.sqrt(c.obs_var))),
                           truth, ensemble, time_varying=True)


@dataclasses.dataclass(frozen=True)
class VolatilityConfig:
    """``x_k = phi x_{k-1} + sigma v_k``, ``y_k = exp(x_k / 2) eps_k``: log-variance x."""

    phi: float = 0.95
    sigma: float = 0.3
    num_steps: int = 200

    def __post_init__(self):
        _checks.check_fields(self, positive=("sigma", "num_steps"))
        if not abs(self.phi) < 1:
            raise ValueError(f"VolatilityConfig.phi must lie in (-1, 1) (a stationary AR(1)), got "
                             f"{self.phi!r}")


@functools.cache
def stochastic_volatility(c: VolatilityConfig = VolatilityConfig()) -> StateSpaceModel:
    stationary = c.sigma / np.sqrt(1.0 - c.phi ** 2)
    truth, ensemble = _gaussian_start([0.0], stationary)
    return StateSpaceModel("stochastic_volatility", 1, 1, c.num_steps, 1.0, lambda x: c.phi * x,
                           lambda x: x, c.sigma, volatility_likelihood(), truth, ensemble)


@dataclasses.dataclass(frozen=True)
class PoissonConfig:
    """Two log-intensities, ``x_k = radius R(angle) x_{k-1} + v_k``, counts
    ``y_j ~ Poisson(exp(level + x_j))``."""

    radius: float = 0.9
    angle: float = 0.3
    process_std: float = 0.3
    level: float = 1.0
    num_steps: int = 100

    def __post_init__(self):
        _checks.check_fields(self, positive=("process_std", "num_steps"))
        if not 0 <= self.radius < 1:
            raise ValueError(f"PoissonConfig.radius must lie in [0, 1) (a stationary process), got "
                             f"{self.radius!r}")


@functools.cache
def poisson_counts(c: PoissonConfig = PoissonConfig()) -> StateSpaceModel:
    A = c.radius * np.array([[np.cos(c.angle), -np.sin(c.angle)],
                             [np.sin(c.angle), np.cos(c.angle)]], np.float32)
    stationary = c.process_std / np.sqrt(1.0 - c.radius ** 2)

    def drift(x):
        return jnp.asarray(A, x.dtype) @ x

    truth, ensemble = _gaussian_start([0.0, 0.0], stationary)
    return StateSpaceModel("poisson_counts", 2, 2, c.num_steps, 1.0, drift,
                           lambda x: c.level + x, c.process_std, poisson_likelihood(), truth,
                           ensemble)


@dataclasses.dataclass(frozen=True)
class LotkaVolterraConfig:
    """Predators and prey in log-populations ``(u, v)``, an Euler step of ``u' = a - b exp(v)``,
    ``v' = d exp(u) - c`` (time step ``dt``), prey counts ``y ~ Poisson(exp(u))``; the predators
    are never seen. The drift is exponential in the state: a member placed far up the unseen
    predator axis drives the prey to ``-1e13`` within a step."""

    a: float = 1.0
    b: float = 0.1
    c: float = 1.5
    d: float = 0.075
    dt: float = 0.05
    process_std: float = 0.05
    start: tuple = (2.3, 1.6)
    start_std: float = 0.2
    num_steps: int = 100

    def __post_init__(self):
        _checks.check_fields(self, positive=("a", "b", "c", "d", "dt", "process_std",
                                             "start_std", "num_steps"))
        _numbers(self, "start", (2,))


@functools.cache
def lotka_volterra(c: LotkaVolterraConfig = LotkaVolterraConfig()) -> StateSpaceModel:
    def drift(x):
        u, v = x[0], x[1]
        return jnp.stack([u + c.dt * (c.a - c.b * jnp.exp(v)), v + c.dt * (c.d * jnp.exp(u) - c.c)])

    truth, ensemble = _gaussian_start(c.start, c.start_std)
    return StateSpaceModel("lotka_volterra", 2, 1, c.num_steps, c.dt, drift, lambda x: x[:1],
                           c.process_std, poisson_likelihood(), truth, ensemble)


@dataclasses.dataclass(frozen=True)
class Linear20Config:
    """``csf_jax.problems.linear.linear_gaussian(20)`` observed at every other coordinate."""

    dim: int = 20
    q_std: float = 0.3
    r_std: float = 0.5
    num_steps: int = 100

    def __post_init__(self):
        _checks.check_fields(self, positive=("dim", "q_std", "r_std", "num_steps"))


@functools.cache
def linear20_gaussian(c: Linear20Config = Linear20Config()):
    """The ``LinearGaussian`` (for the Kalman filter) of ``linear20``."""
    H = np.eye(c.dim)[::2]
    return linear_gaussian(c.dim, H.shape[0], H=H, q_std=c.q_std, r_std=c.r_std,
                           num_steps=c.num_steps, name="linear20")


def linear20(c: Linear20Config = Linear20Config()) -> StateSpaceModel:
    return to_model(linear20_gaussian(c))


@dataclasses.dataclass(frozen=True)
class WellChainConfig:
    """A ring of ``dim`` double wells, ``dx_i/dt = x_i - x_i^3 + coupling (x_{i-1} + x_{i+1} -
    2 x_i)``, ``substeps`` split steps of ``h = dt / substeps`` per filter step (an Euler step of
    the linear part, then the exact flow ``x / sqrt(1 + 2 h x^2)`` of ``-x^3``, stable from any
    state a filter's update reaches), ``x^3`` seen at every ``obs_every``-th site from site 1;
    truth and ensemble start from ``N(0, init_std^2 I)``."""

    dim: int = 16
    dt: float = 0.5
    substeps: int = 5
    coupling: float = 0.5
    process_std: float = 0.2
    obs_every: int = 2
    obs_std: float = 0.2
    init_std: float = 1.0
    num_steps: int = 100

    def __post_init__(self):
        _checks.check_fields(self, positive=("dim", "dt", "substeps", "obs_every", "obs_std",
                                             "init_std", "num_steps"),
                             nonnegative=("coupling", "process_std"))
        if self.dim % self.obs_every:
            raise ValueError(f"WellChainConfig.obs_every ({self.obs_every}) must divide dim "
                             f"({self.dim})")


@functools.cache
def well_chain(c: WellChainConfig = WellChainConfig()) -> StateSpaceModel:
    h = c.dt / c.substeps

    def split_step(i, x):
        x = x + h * (x + c.coupling * (jnp.roll(x, 1) + jnp.roll(x, -1) - 2.0 * x))
        return x * jax.lax.rsqrt(1.0 + 2.0 * h * x * x)

    def drift(x):
        return jax.lax.fori_loop(0, c.substeps, split_step, x)

    truth, ensemble = _gaussian_start(np.zeros(c.dim), c.init_std)
    return StateSpaceModel("well_chain", c.dim, c.dim // c.obs_every, c.num_steps, c.dt, drift,
                           lambda x: x[1::c.obs_every] ** 3, c.process_std,
                           gaussian_noise(c.obs_std), truth, ensemble)


L96_SENSORS = {"abs": jnp.abs, "square": lambda x: 0.25 * x * x}


@dataclasses.dataclass(frozen=True)
class Lorenz96SensorConfig:
    """Lorenz-96 (F = 8, RK4 step ``dt``) with additive process noise, a sign-blind sensor
    (``"abs"``: ``|x|``; ``"square"``: ``x^2 / 4``) at every ``obs_every``-th site; truth and
    ensemble start from a point on the attractor plus ``N(0, x0_std^2 I)``."""

    name: str = "lorenz96_abs"
    dim: int = 40
    sensor: str = "abs"
    obs_every: int = 2
    obs_std: float = 1.0
    dt: float = 0.05
    process_std: float = 0.1
    x0_std: float = 1.0
    num_steps: int = 200

    def __post_init__(self):
        _checks.check_fields(self, positive=("dim", "obs_every", "obs_std", "dt", "x0_std",
                                             "num_steps"), nonnegative=("process_std",))
        if self.sensor not in L96_SENSORS:
            raise ValueError(f"Lorenz96SensorConfig.sensor must be one of {tuple(L96_SENSORS)}, "
                             f"got {self.sensor!r}")
        if self.dim < 4 or self.dim % self.obs_every:
            raise ValueError(f"Lorenz96SensorConfig: dim ({self.dim}) must be >= 4 and a "
                             f"multiple of obs_every ({self.obs_every})")


@functools.cache
def lorenz96_sensor(c: Lorenz96SensorConfig = Lorenz96SensorConfig()) -> StateSpaceModel:
    start = attractor_point(Lorenz96Config(dim=c.dim, dt=c.dt))
    sensor = L96_SENSORS[c.sensor]
    truth, ensemble = _gaussian_start(start, c.x0_std)
    return StateSpaceModel(c.name, c.dim, c.dim // c.obs_every, c.num_steps, c.dt,
                           lambda x: rk4_step(x, c.dt, 8.0),
                           lambda x: sensor(x[::c.obs_every]), c.process_std,
                           gaussian_noise(c.obs_std), truth, ensemble)


BUILDERS = {PendulumConfig: pendulum, Lorenz63Config: lorenz63, BearingsConfig: bearings,
            FoldingConfig: folding, UNGMConfig: ungm, VolatilityConfig: stochastic_volatility,
            PoissonConfig: poisson_counts, LotkaVolterraConfig: lotka_volterra,
            Linear20Config: linear20, WellChainConfig: well_chain,
            Lorenz96SensorConfig: lorenz96_sensor}

CONFIGS = {"pendulum": PendulumConfig(), "lorenz63_gaps": Lorenz63Config(),
           "bearings": BearingsConfig(), "folding": FoldingConfig(), "ungm": UNGMConfig(),
           "stochastic_volatility": VolatilityConfig(), "poisson_counts": PoissonConfig(),
           "lotka_volterra": LotkaVolterraConfig(),
           "linear20": Linear20Config(), "well_chain": WellChainConfig(),
           "lorenz96_abs": Lorenz96SensorConfig(),
           "lorenz96_square": Lorenz96SensorConfig(name="lorenz96_square", dim=20,
                                                   sensor="square")}

# The models of moderate dimension (no near-exact reference exists for them).
MODERATE = ("well_chain", "lorenz96_abs", "lorenz96_square")

# The benchmark's missing observations: each zoo model's share of observation times removed.
ZOO_GAPS = {"lorenz63_gaps": 0.3}
