"""The actor's problem and what a step carries: the shape of the optimization (:class:`ActorProblem`),
one step's result (:class:`ActorStep`), the counters (:class:`ActorCounters`), one robot's memory
between steps (:class:`ActorMemory`), and the nearest convex critic (:func:`nearest_psd_weights`).

The problem is built from an :class:`ActorProblem` by common/math/actor_nlp.py and stepped by
:class:`common.math.actor.StackedActor`; the objectives are in docs/concepts.md.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from common.math.agents import Agent, agent_row
from common.math.arrival import ArrivalRule
from common.math.features import feature_index_pairs
from common.math.integrators import PREDICTORS
from common.math.stats import Window
from common.math.systems import System, check_box_and_cost, system_row


@dataclass(frozen=True)
class ActorProblem:
    """Everything that fixes the shape of the optimization problem (changing it = rebuild)."""

    agent: Agent
    horizon: int  # N: N - 1 held actions, N predicted states
    sampling_time: float
    cost_diag: tuple[float, ...]  # diag(R) over (s, u): the system's state_dim + action_dim
    action_max: tuple[float, ...]  # the box |u_i| <= action_max[i]: the unicycle's (v_max, omega_max)
    predictor: str = "euler"
    solver: str = "fatrop"
    jit: bool = True
    jit_cache: str = ""  # a directory of compiled objects kept across builds ("" = none): common/system/jit.py
    max_iter: int = 100
    tolerance: float = 1e-8
    mu_init: float = 0.01  # interior-point barrier start; small suits the warm start (the solvers' default is 0.1)
    # How far the interior point pushes the initial guess off the action bounds (the solvers'
    # bound_push and bound_frac). The defaults (0.01) move a saturated warm start inward and
    # cost iterations to walk it back; 1e-4 keeps it (docs/benchmarks/).
    bound_push: float = 1e-4
    # The wheel-speed box: a differential drive limits each wheel, not v and omega apart:
    # |v +/- omega * wheel_separation / 2| <= wheel_speed_max * wheel_radius. 0 = off (the
    # paper's method boxes v and omega only). See :attr:`wheel_rim_speed`.
    wheel_speed_max: float = 0.0  # [rad/s] at the wheel
    wheel_radius: float = 0.033  # [m] TurtleBot3 Burger
    wheel_separation: float = 0.160  # [m] TurtleBot3 Burger
    # The actor uses the nearest positive semi-definite quadratic to each learned critic
    # (:func:`nearest_psd_weights`) instead of the critic as fitted (the paper's): a fitted Qhat
    # indefinite in (s, u) predicts negative costs near the target that only motion reaches, and
    # the actor chases them at full speed (docs/experiment.md, chatter). Not a shape change.
    convex_critics: bool = False
    # The argmin (docs/concepts.md, "The argmin"; common/math/actor_search.py): every tick, in one
    # compiled call, the warm plan polished by projected Newton iterations, the robot's alternative
    # plans descended a little further (a global search spread over the ticks), the lowest of them
    # polished where it may win, and a vertex search; the solver only where the Newton iterations
    # fall short. False: the paper's actor, the solver from the cheaper of the shifted and the
    # earlier plan (merit only), which with non-convex critics often stays in a worse local minimum.
    multistart: bool = False
    multistart_starts: int = 4  # alternative plans each robot keeps and descends every tick
    multistart_iterations: int = 10  # projected-gradient iterations per alternative and tick (~1 us each at N = 12)
    # An alternative is polished when its objective is below the warm answer's, or within this share
    # of it once it has descended for a few ticks (actor_search.MATURE); one that stays beyond it is
    # renewed (actor_search.RETIRE).
    multistart_margin: float = 0.1
    # After the polish, up to this many sweeps of the vertex search: every single decision entry
    # set to either bound, the lowest of these 2 (N - 1) x 2 neighbours along the rollout taken
    # while it lowers the objective, then polished (kept when lower). An indefinite critic is
    # concave along some action directions: along them a local minimum sits on one bound while the
    # other may be lower, which no descent can see. 0: off.
    multistart_flips: int = 3
    # The polish: at most this many projected Newton iterations on the single-shooting objective
    # (~8 us each at N = 12), each skipped once the projected gradient is below
    # actor_search.NEWTON_TOLERANCE; the solver (fatrop) only where they end short of it.
    newton_iterations: int = 20
    # The sampled system (a row of common/math/systems.py SYSTEMS): its model is the predictor's,
    # its dimensions the problem's.
    system: str = "unicycle"

    def __post_init__(self) -> None:
        agent_row(self.agent)  # an unknown agent: one line naming the known ones
        system = system_row(self.system)  # an unknown system: one line naming the known ones
        n, m = system.state_dim, system.action_dim
        if self.horizon < 2:
            raise ValueError(f"horizon N must be >= 2 (N - 1 >= 1 actions), got {self.horizon}")
        if not (np.isfinite(self.sampling_time) and self.sampling_time > 0):
            raise ValueError(f"sampling_time must be a positive number, got {self.sampling_time}")
        check_box_and_cost(self.action_max, self.cost_diag, n, m)
        if self.predictor not in PREDICTORS:
            raise ValueError(f"unknown predictor {self.predictor!r}; choose one of {sorted(PREDICTORS)}")
        if self.solver not in ("fatrop", "ipopt"):
            raise ValueError(f"unknown solver {self.solver!r}; choose fatrop or ipopt")
        if not (np.isfinite(self.mu_init) and self.mu_init > 0):
            raise ValueError(f"mu_init must be a positive number, got {self.mu_init}")
        if not (np.isfinite(self.bound_push) and 0 < self.bound_push <= 0.5):
            raise ValueError(f"bound_push must be in (0, 0.5], got {self.bound_push}")
        if not (np.isfinite(self.multistart_margin) and self.multistart_margin >= 0):
            raise ValueError(f"multistart_margin must be a number >= 0, got {self.multistart_margin}")
        if not 1 <= self.multistart_starts <= 32:
            raise ValueError(f"multistart_starts must be 1..32, got {self.multistart_starts}")
        if not 1 <= self.multistart_iterations <= 1000:
            raise ValueError(f"multistart_iterations must be 1..1000, got {self.multistart_iterations}")
        if not 0 <= self.multistart_flips <= 10:
            raise ValueError(f"multistart_flips must be 0..10 (0 = off), got {self.multistart_flips}")
        if not 1 <= self.newton_iterations <= 50:
            raise ValueError(f"newton_iterations must be 1..50, got {self.newton_iterations}")
        if not (np.isfinite(self.wheel_speed_max) and self.wheel_speed_max >= 0):
            raise ValueError(f"wheel_speed_max must be >= 0 (0 = no wheel box), got {self.wheel_speed_max}")
        if self.wheel_speed_max > 0 and not system.wheeled:
            raise ValueError(f"the wheel box (wheel_speed_max > 0) is a wheeled robot's; {self.system} has no wheels")
        for name in ("wheel_radius", "wheel_separation"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")

    @property
    def dynamics(self) -> System:
        """The system's row: its model, dimensions and box (common/math/systems.py)."""
        return system_row(self.system)

    @property
    def state_dim(self) -> int:
        return len(system_row(self.system).states)

    @property
    def action_dim(self) -> int:
        return len(self.action_max)

    @property
    def v_max(self) -> float:
        """A wheeled robot's speed bound [m/s]: ``action_max[0]``."""
        return self.action_max[0]

    @property
    def omega_max(self) -> float:
        """A wheeled robot's turning-rate bound [rad/s]: ``action_max[1]``."""
        return self.action_max[1]

    @property
    def wheel_box(self) -> bool:
        return self.wheel_speed_max > 0

    @property
    def wheel_rim_speed(self) -> float:
        """The bound on each wheel's rim speed ``v +/- omega * separation / 2`` [m/s].

        ``wheel_speed_max * wheel_radius``, but no more than ``v_max`` and
        ``omega_max * separation / 2``: then the wheel box (a diamond in (v, omega)) lies inside
        the (v, omega) box and is the only bound the problem needs, as simple bounds on the
        wheels' rim speeds (the decision variables when the box is on). TurtleBot3 Burger:
        6.67 rad/s x 0.033 m = 0.2201 m/s, held to v_max = 0.22 m/s; the largest omega is then
        0.22 / 0.08 = 2.75 rad/s < 2.84."""
        half_track = 0.5 * self.wheel_separation
        return min(self.wheel_speed_max * self.wheel_radius, self.v_max, self.omega_max * half_track)

    @property
    def action_matrix(self) -> np.ndarray:
        """``T`` with (v, omega) = ``T`` d for one stage's decision variables d: the identity,
        or with the wheel box on, d = the wheels' rim speeds (right, left), v = (r + l) / 2,
        omega = (r - l) / separation. Linear, so the problem keeps its stage-wise structure."""
        if not self.wheel_box:
            return np.eye(self.action_dim)
        return np.array([[0.5, 0.5], [1.0 / self.wheel_separation, -1.0 / self.wheel_separation]])

    @property
    def decision_bounds(self) -> list[float]:
        """The box on one stage's decision variables: the wheels' rim speeds with the wheel box
        on (:attr:`wheel_rim_speed` each), else :attr:`action_max` (the unicycle's ``(v_max, omega_max)``)."""
        return [self.wheel_rim_speed] * 2 if self.wheel_box else list(self.action_max)


@functools.cache
def _pair_indices(dim: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows, columns (common.math.features' order) and 1 / 2 (diagonal / off) of the quadratic's weights."""
    rows, cols = np.array(feature_index_pairs(dim)).T
    return rows, cols, np.where(rows == cols, 1.0, 2.0)


def _quadratic_matrix(weights: np.ndarray, dim: int) -> np.ndarray:
    """The symmetric ``M`` with ``<weights, phi(z)> = z^T M z`` (features: common.math.features)."""
    rows, cols, scale = _pair_indices(dim)
    matrix = np.zeros((dim, dim))
    matrix[rows, cols] = weights / scale
    matrix[cols, rows] = weights / scale  # diagonal: w_ii; off-diagonal: w_ij / 2 on both sides
    return matrix


def nearest_psd_weights(weights: np.ndarray, dim: int) -> np.ndarray:
    """The weights of the nearest (Frobenius) positive semi-definite quadratic to
    ``<weights, phi(z)>``: its matrix with the negative eigenvalues set to zero. A PSD quadratic
    is never negative, as a cost-to-go of a non-negative stage cost never is. ~10-20 us."""
    eigenvalues, vectors = np.linalg.eigh(_quadratic_matrix(weights, dim))
    if eigenvalues[0] >= 0.0:
        return np.array(weights, dtype=float)
    projected = (vectors * np.maximum(eigenvalues, 0.0)) @ vectors.T
    rows, cols, scale = _pair_indices(dim)
    out: np.ndarray = scale * projected[rows, cols]
    return out


@dataclass
class ActorStep:
    """What one actor step produced. ``action`` is always finite and within bounds."""

    action: np.ndarray
    plan: np.ndarray  # (N-1, action_dim) held actions, u_1 first
    objective: float  # nan: no solution (a failed solve, or "arrived": no solve)
    success: bool
    solve_seconds: float
    status: str


# What a step can run (StackedActor.step, common/math/actor_search.py): the warm polish, the
# search (the alternatives' descent), the polish of an alternative, the cold lane's polish, the
# vertex search, the polish of where it ended, and the solver where the Newton iterations fell short.
PHASES = ("warm_polish", "search", "alternative_polish", "cold_polish", "vertex_search", "vertex_polish", "solver")


@dataclass
class ActorCounters:
    """Solves, failures and the step times (a fixed window: an actor runs for days; the rest are sums)."""

    solves: int = 0
    failures: int = 0
    arrived_steps: int = 0  # steps at which the arrival rule held the robot (no solve)
    hurried_solves: int = 0  # steps solved in a hurry: the warm polish only (no search, no vertex search)
    alternative_wins: int = 0  # steps whose answer is a polished alternative plan (the search)
    vertex_wins: int = 0  # steps whose answer the vertex search found
    repolished: int = 0  # steps whose polish ended short of stationary and went on for another tick's iterations
    solve_seconds: Window = field(default_factory=Window)
    # per phase (PHASES): the steps that ran it; and the seconds of the compiled search calls
    # (the rest of a step's time is the Python around them and the solver)
    phase_counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(PHASES, 0))
    search_seconds: float = 0.0
    solver_seconds: float = 0.0


@dataclass
class ActorMemory:
    """What one robot's actor carries from one step to the next: its last two plans (the warm
    starts), its alternative plans and their ages (the search, common/math/actor_search.py), the
    next row of the fresh-start table, its arrival rule and its counters. Everything else of a
    :class:`~common.math.actor.StackedActor` (the compiled problem and its buffers, which every
    step rewrites completely before solving) holds nothing between steps, so one built actor
    serves many robots, one step at a time, each with its own memory
    (:meth:`~common.math.actor.StackedActor.swap_memory`; services/actor/host.py)."""

    previous_x: np.ndarray | None = None
    earlier_x: np.ndarray | None = None
    arrival: ArrivalRule | None = None
    counters: ActorCounters = field(default_factory=ActorCounters)
    alternatives: np.ndarray | None = None  # (multistart_starts, 2 (N - 1)) scaled plans; None: none yet
    ages: np.ndarray | None = None  # ticks each alternative has descended
    fresh: int = 0  # the next row of the fresh-start table (actor_search.fresh_starts)

    def forget(self) -> None:
        """A new episode (or the plans no longer match the robot): no plans, no arrival; counters kept."""
        self.previous_x = self.earlier_x = None
        self.alternatives = self.ages = None
        self.fresh = 0
        if self.arrival is not None:
            self.arrival.reset()

    def held_at_rest(self) -> None:
        """A step at which the arrival rule holds the robot (it said "arrived" and the state is
        within its tolerances): exactly zero, no solve; the plans are void (resuming starts cold)."""
        self.previous_x = self.earlier_x = None
        self.counters.arrived_steps += 1
