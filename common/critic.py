"""The double critic and its temporal-difference least-squares fit (section III, eq. critic-cost).

``Qhat(s, u; w) = <w, phi_Q(s, u)>`` and ``Jhat(s; v) = <v, phi_V(s)>``. Over a replay of the
last ``M`` samples ``(s_j, u_j, c_j)`` of one episode (``M - 1`` consecutive pairs; a gap in the
step index ``j`` breaks the pair) the TD errors are

    e_j(w) = <w, phi_Q(s_j, u_j)> - beta <w_prev, phi_Q(s_{j+1}, u_{j+1})> - c_j
    e_j(v) = <v, phi_V(s_j)>      - beta <v_prev, phi_V(s_{j+1})>       - c_j

and the fit minimizes ``1/2 sum e_j^2 + lambda/2 |w - w_prev|^2`` (optionally within box
bounds). With ``w_prev`` frozen that is LINEAR least squares, solved as such: ``numpy.lstsq``
without bounds, ``scipy.optimize.lsq_linear`` (BVLS) with them -- or, when the last fit's set of
weights on a bound is still optimal, one ``lstsq`` on the others (:func:`bounded_lstsq`).

Underdetermined fits (fewer pairs than weights, e.g. early in an episode or ``M < 16``): we
solve for the change ``dw = w - w_prev`` and take the minimum-norm ``dw``, i.e. the weights
closest to the previous ones that fit the TDs best. That is the limit of the ridge as
``lambda -> 0`` and it leaves weights untouched in directions the data does not see.

A fleet may pool its learning (issue 16): :class:`PooledReplay` keeps the last ``M`` samples of
each robot's episode, and ONE :class:`DoubleCritic` is fitted on the TD pairs of all of them
together. A pair is formed only within one robot's stream of consecutive steps, never across two
robots or across a gap. A pool of one robot is the per-robot learner, bit for bit (the same
design, built by the same code: :func:`stream_design`).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import lsq_linear

from common.agents import fit_due
from common.features import Q_FEATURES, phi_q, phi_q_rows, phi_v, phi_v_rows

Features = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class Sample:
    """One replay entry: the step index, the state, the held action and its interval cost."""

    step: int
    state: np.ndarray
    action: np.ndarray
    cost: float  # c_j = delta * r(s_j, u_j)


@dataclass(frozen=True)
class FitResult:
    weights: np.ndarray
    residual: float  # 1/2 sum e_j^2 at the new weights (the TD part, ridge excluded)
    pairs: int
    # Bounded fits: which weights ended on a bound (-1 low, +1 high, 0 free); the next fit's guess.
    on_bound: np.ndarray | None = None


def consecutive_pairs(steps: Sequence[int]) -> list[tuple[int, int]]:
    """Indices ``(a, b)`` into ``steps`` with ``steps[b] == steps[a] + 1`` and ``b == a + 1``.

    Only neighbours in the replay can pair, and only if no step is missing between them:
    a gap (lost or not yet received sample) is never bridged.
    """
    return [(a, a + 1) for a in range(len(steps) - 1) if steps[a + 1] == steps[a] + 1]


KKT_TOLERANCE = 1e-10  # scipy's lsq_linear default ``tol``: the largest KKT violation accepted


def bounded_lstsq(
    a: np.ndarray, b: np.ndarray, low: np.ndarray, high: np.ndarray, guess: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``min |a x - b|`` subject to ``low <= x <= high``: ``(x, on_bound)``.

    ``guess``: the ``on_bound`` of a previous, similar problem (the critic's last fit). If the
    least squares on its free columns, with the others held at their bounds, is within the bounds
    and meets the KKT conditions (scipy's test and tolerance), that is the minimum: ONE ``lstsq``.
    Otherwise scipy's BVLS (``lsq_linear``) solves it, as it always did. Use a guess only for a
    strictly convex problem (full column rank, e.g. with a ridge): its minimum is unique, so both
    ways reach the same ``x`` (to rounding) and the guess changes the cost, never the answer.
    """
    n = a.shape[1]
    if guess is not None and guess.shape == (n,):
        free = guess == 0
        x = np.where(guess < 0, low, np.where(guess > 0, high, 0.0))
        z = np.linalg.lstsq(a[:, free], b - a @ (x * ~free), rcond=None)[0]
        if np.all(z >= low[free]) and np.all(z <= high[free]):
            x[free] = z
            gradient = a.T @ (a @ x - b)
            violation = gradient * guess  # > 0: moving off its bound would lower the cost
            violation[free] = np.abs(gradient[free])
            if float(np.max(violation)) < KKT_TOLERANCE:
                return x, guess.copy()
    solution = lsq_linear(a, b, bounds=(low, high), method="bvls", tol=KKT_TOLERANCE)
    return solution.x, np.asarray(solution.active_mask, dtype=float)


def td_fit(
    features_now: np.ndarray,
    features_next: np.ndarray,
    costs: np.ndarray,
    previous_weights: np.ndarray,
    discount: float,
    ridge: float = 0.0,
    bounds: tuple[float, float] | None = None,
    on_bound: np.ndarray | None = None,
) -> FitResult:
    """Least-squares TD fit of linear weights, dimension-generic.

    ``features_now[j] = phi(z_j)``, ``features_next[j] = phi(z_{j+1})``, ``costs[j] = c_j``;
    targets are ``c_j + discount * <previous_weights, phi(z_{j+1})>``. ``on_bound``: the last
    bounded fit's (:attr:`FitResult.on_bound`), a guess that makes this one cheaper when the
    ridge makes the problem strictly convex (:func:`bounded_lstsq`); the result is the same.
    """
    previous = np.asarray(previous_weights, dtype=float)
    a = np.atleast_2d(np.asarray(features_now, dtype=float))
    pairs = a.shape[0] if np.size(costs) else 0
    if pairs == 0:
        return FitResult(previous.copy(), 0.0, 0, on_bound)
    targets = np.asarray(costs, float) + discount * (np.asarray(features_next, float) @ previous)
    # Solve for dw = w - w_prev: A dw ~ targets - A w_prev, with the ridge as extra rows.
    rhs = targets - a @ previous
    if ridge > 0:
        a_aug = np.vstack([a, np.sqrt(ridge) * np.eye(previous.size)])
        rhs_aug = np.concatenate([rhs, np.zeros(previous.size)])
    else:
        a_aug, rhs_aug = a, rhs
    active = None
    if bounds is None:
        delta_w = np.linalg.lstsq(a_aug, rhs_aug, rcond=None)[0]
        weights = previous + delta_w
    else:
        low, high = bounds
        # The previous weights may sit outside new bounds: clip before measuring the change.
        base = np.clip(previous, low, high)
        rhs_b = rhs_aug - a_aug @ (base - previous)
        step, active = bounded_lstsq(a_aug, rhs_b, low - base, high - base, on_bound if ridge > 0 else None)
        weights = np.clip(base + step, low, high)
    errors = a @ weights - targets
    return FitResult(weights, 0.5 * float(errors @ errors), pairs, active)


class Replay:
    """The last ``capacity`` samples of ONE episode, kept in step order."""

    def __init__(self, capacity: int) -> None:
        if capacity < 2:
            raise ValueError(f"replay size M must be >= 2 (one TD pair), got {capacity}")
        self.capacity = capacity
        self._samples: deque[Sample] = deque(maxlen=capacity)

    def __len__(self) -> int:
        return len(self._samples)

    @property
    def samples(self) -> list[Sample]:
        return list(self._samples)

    def clear(self) -> None:
        self._samples.clear()

    def add(self, sample: Sample) -> None:
        """Insert in step order; a duplicate step replaces nothing and raises."""
        if self._samples and sample.step <= self._samples[-1].step:
            if any(s.step == sample.step for s in self._samples):
                raise ValueError(f"step {sample.step} is already in the replay")
            # Late arrival (out of order): insert where it belongs, then trim the oldest.
            items = sorted([*self._samples, sample], key=lambda s: s.step)[-self.capacity :]
            self._samples = deque(items, maxlen=self.capacity)
            return
        self._samples.append(sample)

    def design(self, features: Features) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(features_now, features_next, costs)`` over the consecutive pairs.

        ``features(states, actions)`` maps the replay's stacked states ``(n, 3)`` and actions
        ``(n, 2)`` to one feature row per sample (vectorized: one call per fit, not per sample).
        """
        return stream_design([self._samples], features)


def stream_design(streams: Iterable[Sequence[Sample]], features: Features) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The TD design of several sample streams, each in step order: ``(features_now,
    features_next, costs)`` over every stream's consecutive pairs, stream after stream.

    A pair joins two neighbours of ONE stream whose steps differ by one; the streams are laid end
    to end only after pairing, so no pair ever joins the last sample of one stream to the first of
    the next. The features are computed in one call over all samples.
    """
    samples: list[Sample] = []
    now: list[int] = []
    for stream in streams:
        items = list(stream)
        offset = len(samples)
        now.extend(offset + a for a, _ in consecutive_pairs([s.step for s in items]))
        samples.extend(items)
    if not now:
        return np.empty((0, 0)), np.empty((0, 0)), np.empty(0)
    phis = features(np.array([s.state for s in samples]), np.array([s.action for s in samples]))
    now_index = np.array(now, dtype=np.intp)
    costs = np.array([samples[a].cost for a in now])
    return phis[now_index], phis[now_index + 1], costs


class PooledReplay:
    """The last ``capacity`` samples of each robot's episode: one :class:`Replay` per robot (its
    stream), one design over all of them (pairs only within a stream). Memory: at most
    ``capacity`` samples per robot held."""

    def __init__(self, capacity: int) -> None:
        Replay(capacity)  # the same check of M
        self.capacity = capacity
        self.streams: dict[str, Replay] = {}

    def __len__(self) -> int:
        return sum(len(replay) for replay in self.streams.values())

    def stream(self, robot: str) -> Replay:
        """The robot's replay (created empty on first use)."""
        replay = self.streams.get(robot)
        if replay is None:
            replay = self.streams[robot] = Replay(self.capacity)
        return replay

    def restart(self, robot: str) -> Replay:
        """The robot starts a new episode: its stream starts empty (the others keep theirs)."""
        replay = self.streams[robot] = Replay(self.capacity)
        return replay

    def add(self, robot: str, sample: Sample) -> None:
        self.stream(robot).add(sample)

    def clear(self) -> None:
        self.streams.clear()

    def design(self, features: Features) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every stream's consecutive pairs, stacked (robots in the order they joined)."""
        return stream_design([replay.samples for replay in self.streams.values()], features)


@dataclass
class CriticUpdate:
    q: FitResult
    v: FitResult


class DoubleCritic:
    """``Qhat`` and ``Jhat`` with their weights; :meth:`update` runs one TD fit of both."""

    def __init__(
        self,
        q_weights: np.ndarray,
        v_weights: np.ndarray,
        discount: float,
        ridge: float = 0.0,
        bounds: tuple[float, float] | None = None,
    ) -> None:
        if not 0.0 <= discount <= 1.0:
            raise ValueError(f"discount beta must lie in [0, 1], got {discount}")
        if ridge < 0:
            raise ValueError(f"ridge lambda must be >= 0, got {ridge}")
        if bounds is not None and not bounds[0] < bounds[1]:
            raise ValueError(f"weight bounds must satisfy low < high, got {bounds}")
        self.q_weights = np.asarray(q_weights, dtype=float).copy()
        self.v_weights = np.asarray(v_weights, dtype=float).copy()
        for name, w in (("q", self.q_weights), ("v", self.v_weights)):
            if not np.all(np.isfinite(w)):
                raise ValueError(f"initial {name} weights must be finite")
        self.discount = discount
        self.ridge = ridge
        self.bounds = bounds
        # Each critic's last bounded fit: which weights ended on a bound (the next fit's guess).
        self.q_on_bound: np.ndarray | None = None
        self.v_on_bound: np.ndarray | None = None

    def q_value(self, state: np.ndarray, action: np.ndarray) -> float:
        return float(self.q_weights @ phi_q(state, action))

    def value(self, state: np.ndarray) -> float:
        return float(self.v_weights @ phi_v(state))

    def update(self, replay: Replay | PooledReplay) -> CriticUpdate:
        """One TD least-squares fit of both critics on the replay (Algorithm 1, line 6).

        One design for both: the replay's pairs and arrays are built once, phi_Q and phi_V
        computed side by side (each column as :func:`phi_q_rows` / :func:`phi_v_rows` alone)."""
        args = (self.discount, self.ridge, self.bounds)
        now, following, costs = replay.design(_phi_qv_rows)
        q = Q_FEATURES
        q_fit = td_fit(_columns(now, 0, q), _columns(following, 0, q), costs, self.q_weights, *args, self.q_on_bound)
        v_fit = td_fit(_columns(now, q), _columns(following, q), costs, self.v_weights, *args, self.v_on_bound)
        # Never accept a non-finite fit (ill-conditioned data): keep the previous weights.
        if np.all(np.isfinite(q_fit.weights)):
            self.q_weights, self.q_on_bound = q_fit.weights, q_fit.on_bound
        if np.all(np.isfinite(v_fit.weights)):
            self.v_weights, self.v_on_bound = v_fit.weights, v_fit.on_bound
        return CriticUpdate(q_fit, v_fit)


def _phi_qv_rows(states: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """phi_Q's Q_FEATURES columns, then phi_V's."""
    return np.hstack([phi_q_rows(states, actions), phi_v_rows(states)])


def _columns(rows: np.ndarray, start: int, stop: int | None = None) -> np.ndarray:
    """Columns ``start:stop`` as their own contiguous array (the fit's products then run as on a
    design built alone); an empty design stays empty."""
    return np.ascontiguousarray(rows[:, start:stop]) if rows.size else rows


class PooledLearner:
    """ONE :class:`DoubleCritic` learning from a fleet's transitions (issue 16's pooled critic).

    :meth:`record` puts a robot's sample into its stream of the :class:`PooledReplay`; the pool is
    fitted once per ``size`` transitions due a fit (``fit_due``) since its last fit, where ``size``
    is the fleet's robot count (given, or else the robots heard from so far): once per step of a
    fleet stepping together, never once per robot and step (a fleet of K would fit K times as
    often on K times the data). A pool of one fits exactly when the per-robot learner does.
    """

    def __init__(self, critic: DoubleCritic, capacity: int, update_every: int, robots: int | None = None) -> None:
        if update_every < 1:
            raise ValueError(f"update_every must be >= 1, got {update_every}")
        if robots is not None and robots < 1:
            raise ValueError(f"a pool needs at least one robot, got {robots}")
        self.critic = critic
        self.replay = PooledReplay(capacity)
        self.update_every = update_every
        self.robots = robots
        self.due = 0  # transitions due a fit since the last fit

    @property
    def size(self) -> int:
        return self.robots if self.robots is not None else max(1, len(self.replay.streams))

    def record(self, robot: str, sample: Sample) -> bool:
        """Into the robot's stream; True when the pool's fit is now due (:meth:`fit` it)."""
        self.replay.add(robot, sample)
        return self.count(sample.step)

    def count(self, step: int) -> bool:
        """A transition of ``step`` entered a stream: True when the pool's fit is due (the count
        starts again; the caller fits now, or later on more, e.g. at the end of a batch)."""
        if fit_due(step, self.update_every):
            self.due += 1
        if self.due < self.size:
            return False
        self.due = 0
        return True

    def fit(self) -> CriticUpdate:
        """One TD least-squares fit of both critics on every robot's pairs."""
        return self.critic.update(self.replay)
