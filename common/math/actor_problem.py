"""The actor's problem and what a step carries: the shape of the optimization (:class:`ActorProblem`),
one step's result (:class:`ActorStep`), the counters (:class:`ActorCounters`), one robot's memory
between steps (:class:`ActorMemory`), and the nearest convex critic (:func:`nearest_psd_weights`).

The problem is built from an :class:`ActorProblem` by common/math/actor_nlp.py and stepped by
:class:`common.math.actor.StackedActor`; the objectives are in docs/concepts.md.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Literal, get_args

import numpy as np

from common.math.agents import AGENTS, Agent
from common.math.arrival import ArrivalRule
from common.math.dynamics import ACTION_DIM, PREDICTORS, STATE_DIM
from common.math.features import feature_index_pairs
from common.math.stats import Window

# The global phase's starts (ActorProblem.multistart): the shifted and the earlier plan (or, with
# no plan yet, turning in place either way), standing still, full speed ahead, full speed back.
GLOBAL_STARTS = 5
# The polish's Newton iterations are done when the largest entry of the projected gradient (of
# the objective in the box-scaled decisions z in [-1, 1]) is at most this; else the solver goes on
# from their end (common.math.actor.StackedActor._polish).
NEWTON_TOLERANCE = 1e-6
# What a hurried step does once the robot has a plan (ActorProblem.hurry).
Hurry = Literal["polish", "descend"]
HURRIES: tuple[Hurry, ...] = get_args(Hurry)


@dataclass(frozen=True)
class ActorProblem:
    """Everything that fixes the shape of the optimization problem (changing it = rebuild)."""

    agent: Agent
    horizon: int  # N: N - 1 held actions, N predicted states
    sampling_time: float
    cost_diag: tuple[float, ...]  # diag(R), length 5
    v_max: float
    omega_max: float
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
    # The argmin (docs/concepts.md): before the solver, a cheap global phase -- projected-gradient
    # descent on the objective along a rollout, from several starts at once (the shifted and the
    # earlier plan, standing still, full speed ahead, full speed back; :meth:`StackedActor.
    # _global_guess`) -- and the solver polishes the start whose descent ended lowest. False:
    # the solver starts from the cheaper of the shifted and the earlier plan (merit only), which
    # often stays in a worse local minimum with non-convex critics.
    multistart: bool = False
    multistart_iterations: int = 50  # projected-gradient iterations per start (compiled, ~1-3 us each at N = 12)
    # The merit cannot tell: also polish the lowest end of the other kind of start (warm: the
    # shifted and earlier plans; fresh: the other three) when its objective is within this share
    # of the lowest's, and keep the lower solution (StackedActor._runner_up). 0: the lowest only.
    multistart_margin: float = 0.1
    # Every this many solves, polish the other kind of start's lowest end whatever the merit says
    # (a fresh descent may stop far short of a lower minimum: near the target its end often
    # looks worse than a converged warm plan whose basin is worse); the warm start then keeps a
    # lower minimum once found. 0: never (the margin alone decides).
    multistart_refresh: int = 3
    # A runner-up polish that ended above the answer by more than this share (it lost by a lot)
    # predicts the next ones: they are skipped, the margin's as well, until a refresh's
    # (``multistart_refresh``) polish measures again and loses by less or wins. Where the other
    # kind of start keeps descending to a worse minimum (an indefinite critic: 6-7 % worse at 60 %
    # of the steps, none lower) that is a fatrop solve saved per step; where it sometimes wins
    # (losing by 0.2-0.3 % otherwise) nothing changes. 0: never skipped.
    multistart_hopeless: float = 0.0
    # After the polish, a vertex search (StackedActor._flip_search): every single held-action
    # entry set to either bound, the lowest of these 2 (N - 1) x 2 neighbours along the rollout
    # taken while it lowers the objective, up to this many sweeps, and the solver polishes the
    # result (kept when lower). An indefinite critic is concave along some action directions:
    # along them a local minimum sits on one bound while the other may be lower, which neither
    # the descent nor the interior point can see. 0: off.
    multistart_flips: int = 0
    # The global phase (and the runner-up polish, which picks among its ends) at every this many
    # solves of a robot, and at every solve without a plan; the solves between start from the
    # cheaper of the shifted and the earlier plan (as ``multistart`` off) and keep the vertex
    # search. Once a plan has settled the global phase rarely moves the answer, and it is ~40 % of
    # a solve at N = 12; an actor host serving many robots sets it (actor.host_global_every). 1: every solve.
    global_every: int = 1
    # What a hurried step (StackedActor.step ``hurry``) does once the robot has a plan: "polish",
    # one solver polish of the warm start; "descend", the warm start descended by the global
    # phase's compiled projected gradient, no solver (one start: a fifth of the global phase;
    # compiled only with this setting and ``multistart``). An actor host over its CPU budget sets it
    # (actor.host_hurry): what a hurried tick costs is what caps the host's CPU.
    hurry: Hurry = "polish"
    # The polish (of the chosen start, the runner-up, a vertex neighbour): first this many
    # projected Newton iterations on the single-shooting objective, compiled into one call
    # (common.math.actor_nlp.newton_polish, ~10 us each at N = 12), and the solver only where
    # their end is not stationary (projected gradient above NEWTON_TOLERANCE). 0: the solver
    # polishes every start.
    newton_iterations: int = 0

    def __post_init__(self) -> None:
        if self.agent not in AGENTS:
            raise ValueError(f"unknown agent {self.agent!r}; choose one of {', '.join(AGENTS)}")
        if self.horizon < 2:
            raise ValueError(f"horizon N must be >= 2 (N - 1 >= 1 actions), got {self.horizon}")
        if not (np.isfinite(self.sampling_time) and self.sampling_time > 0):
            raise ValueError(f"sampling_time must be a positive number, got {self.sampling_time}")
        if len(self.cost_diag) != STATE_DIM + ACTION_DIM or not all(np.isfinite(c) and c >= 0 for c in self.cost_diag):
            raise ValueError(f"cost_diag must be 5 finite non-negative numbers, got {self.cost_diag}")
        for name in ("v_max", "omega_max"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")
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
        if not (np.isfinite(self.multistart_hopeless) and self.multistart_hopeless >= 0):
            raise ValueError(f"multistart_hopeless must be a number >= 0 (0 = never), got {self.multistart_hopeless}")
        if self.multistart_refresh < 0:
            raise ValueError(f"multistart_refresh must be >= 0 (0 = never), got {self.multistart_refresh}")
        if self.multistart_iterations < 1:
            raise ValueError(f"multistart_iterations must be >= 1, got {self.multistart_iterations}")
        if self.global_every < 1:
            raise ValueError(f"global_every must be >= 1 (1 = every solve), got {self.global_every}")
        if self.hurry not in HURRIES:
            raise ValueError(f"unknown hurry {self.hurry!r}; choose one of {', '.join(HURRIES)}")
        if not 0 <= self.newton_iterations <= 50:
            raise ValueError(f"newton_iterations must be 0..50 (0 = no Newton), got {self.newton_iterations}")
        if self.multistart_flips < 0:
            raise ValueError(f"multistart_flips must be >= 0 (0 = off), got {self.multistart_flips}")
        if not (np.isfinite(self.wheel_speed_max) and self.wheel_speed_max >= 0):
            raise ValueError(f"wheel_speed_max must be >= 0 (0 = no wheel box), got {self.wheel_speed_max}")
        for name in ("wheel_radius", "wheel_separation"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")

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
            return np.eye(ACTION_DIM)
        return np.array([[0.5, 0.5], [1.0 / self.wheel_separation, -1.0 / self.wheel_separation]])

    @property
    def decision_bounds(self) -> list[float]:
        """The box on one stage's decision variables: the wheels' rim speeds with the wheel box
        on (:attr:`wheel_rim_speed` each), else ``(v_max, omega_max)``."""
        return [self.wheel_rim_speed] * ACTION_DIM if self.wheel_box else [self.v_max, self.omega_max]


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
    plan: np.ndarray  # (N-1, 2) held actions, u_1 first
    objective: float  # nan: no solution (a failed solve, or "arrived": no solve)
    success: bool
    solve_seconds: float
    status: str


# The phases of a step (StackedActor.step): the global phase (multistart), the solver's polish
# of the chosen start, the runner-up's polish, the vertex search and the polish of what it found.
PHASES = ("global", "polish", "runner_up", "flip_search", "flip_polish")


@dataclass
class ActorCounters:
    """Solves, failures and the step times (a fixed window: an actor runs for days)."""

    solves: int = 0
    failures: int = 0
    arrived_steps: int = 0  # steps at which the arrival rule held the robot (no solve)
    second_solves: int = 0  # steps that also polished the runner-up end (multistart_margin)
    flip_solves: int = 0  # steps whose vertex search found a lower neighbour and polished it (multistart_flips)
    hurried_solves: int = 0  # steps solved in a hurry: the runner-up polish and vertex search skipped
    newton_fallbacks: int = 0  # polishes whose Newton iterations fell short: the solver went on (newton_iterations)
    solve_seconds: Window = field(default_factory=Window)
    # per phase of a step (PHASES): the steps that ran it and its total time [s] (sums, not lists)
    phase_counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(PHASES, 0))
    phase_seconds: dict[str, float] = field(default_factory=lambda: dict.fromkeys(PHASES, 0.0))

    def add_phase(self, phase: str, seconds: float) -> None:
        """One run of ``phase`` (one of PHASES) that took ``seconds``."""
        self.phase_counts[phase] += 1
        self.phase_seconds[phase] += seconds


@dataclass
class ActorMemory:
    """What one robot's actor carries from one step to the next: its last two plans (the warm
    starts), its arrival rule, its counters and the refresh's phase. Everything else of a
    :class:`~common.math.actor.StackedActor` (the compiled problem and its buffers, which every
    step rewrites completely before solving) holds nothing between steps, so one built actor
    serves many robots, one step at a time, each with its own memory
    (:meth:`~common.math.actor.StackedActor.swap_memory`; services/actor/host.py)."""

    previous_x: np.ndarray | None = None
    earlier_x: np.ndarray | None = None
    arrival: ArrivalRule | None = None
    counters: ActorCounters = field(default_factory=ActorCounters)
    episode_solves: int = 0  # solves since the last reset: the phase of multistart_refresh
    runner_up_shortfall: float = 0.0  # how far the last runner-up polish ended above the answer (multistart_hopeless)
