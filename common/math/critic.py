"""The double critic and its temporal-difference least-squares fit (section III, eq. critic-cost).

``Qhat(s, u; w) = <w, phi_Q(s, u)>`` and ``Jhat(s; v) = <v, phi_V(s)>``. Over a replay of the
last ``M`` samples ``(s_j, u_j, c_j)`` of one episode (``M - 1`` consecutive pairs; a gap in the
step index ``j`` breaks the pair) the TD errors are

    e_j(w) = <w, phi_Q(s_j, u_j)> - beta <w_prev, phi_Q(s_{j+1}, u_{j+1})> - c_j
    e_j(v) = <v, phi_V(s_j)>      - beta <v_prev, phi_V(s_{j+1})>       - c_j

and the fit minimizes ``1/2 sum e_j^2 + lambda/2 |w - w_prev|^2`` (optionally within box
bounds). With ``w_prev`` frozen that is LINEAR least squares. With a ridge (``lambda > 0``, the
default) it is strictly convex and is solved in the weights' space (:func:`fit_gram`):
the Gram matrix ``A^T A + lambda I`` and ``A^T rhs`` of each critic, then one linear solve on the
weights that are not on a bound -- the last fit's set of weights on a bound, checked against the
KKT conditions (scipy's test and tolerance) -- and scipy's BVLS (``lsq_linear``) on the Cholesky
factor only when that set is no longer optimal. Both critics of a robot, and the critics of many
robots (a fleet's critic fits every robot due in one batch), are ONE stacked solve: numpy loops
LAPACK over the stack, so each robot's weights are the same bits whatever the batch
(:func:`update_many`; ``tests/test_critic_batch.py``). Without a ridge (underdetermined early on) it is
``numpy.lstsq`` (:func:`td_fit`).

A :class:`Replay` keeps its samples' TD rows (``phi_Q``, ``phi_V``), steps and costs in ring
buffers, each row computed once as its sample enters; a batch's designs are gathered from them
(:func:`kept_designs`), the same arrays, bit for bit, as built from the samples
(:func:`padded_designs`; ``tests/test_critic_batched.py``).

Underdetermined fits (fewer pairs than weights, e.g. early in an episode or ``M < 16``): we
solve for the change ``dw = w - w_prev`` and take the minimum-norm ``dw``, i.e. the weights
closest to the previous ones that fit the TDs best. That is the limit of the ridge as
``lambda -> 0`` and it leaves weights untouched in directions the data does not see.

A fleet may pool its learning (docs/fleets.md): :class:`PooledReplay` keeps the last ``M`` samples of
each robot's episode, and ONE :class:`DoubleCritic` is fitted on the TD pairs of all of them
together. A pair is formed only within one robot's stream of consecutive steps, never across two
robots or across a gap. A pool of one robot is the per-robot learner, bit for bit (the same
design, built by the same code: :func:`stream_design`).
"""

from __future__ import annotations

import contextlib
import functools
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.math.agents import fit_due
from common.math.arrival import ArrivalTolerances, arrival_masks, arrival_update
from common.math.dynamics import ACTION_DIM, STATE_DIM
from common.math.features import (
    dim_of_features,
    feature_index_pairs,
    phi_q,
    phi_q_rows,
    phi_v,
    phi_v_rows,
)

Features = Callable[[np.ndarray, np.ndarray], np.ndarray]


@functools.cache
def qv_products(state_dim: int, action_dim: int) -> tuple[np.ndarray, np.ndarray]:
    """The products of ``z = (s, u)`` that make a TD row (phi_Q(s, u), then phi_V(s)): phi_Q's
    pairs over ``z``, then phi_V's over ``s = z[:state_dim]`` (common/math/features.py): a row is
    ``z[left] * z[right]``, the products :func:`_phi_qv_rows` makes."""
    pairs = zip(*feature_index_pairs(state_dim + action_dim), *feature_index_pairs(state_dim), strict=True)
    left, right = (np.array(column, dtype=np.intp) for column in pairs)
    return left, right


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


def at_rest(
    previous: Sample | None, sample: Sample, tolerances: ArrivalTolerances | None, inner: bool | None = None
) -> bool:
    """``sample`` is a robot held at rest by the arrival rule (common/math/arrival.py): the step
    after ``previous``, the same state, inside the rule's INNER tolerances (where the rule holds a
    robot whatever it said before), and both held actions exactly zero. Its critic enters it into
    the replay but does not fit on it (nor publishes weights): while the rule holds the robot its
    actor solves nothing and uses no weights, so a fit would only move weights nobody uses. The
    first transition after the robot moves (another state) is fitted on the whole replay, rests
    included. Between the inner and the outer tolerances a zero command may be a robot passing
    through, or the wheel deadband's (then the rule holds the robot: ArrivalRule.last_word); the
    critic cannot tell them apart, so there every due fit is made. ``tolerances`` None (no arrival
    rule, the paper's method): never at rest. ``inner``: whether the state is inside the inner
    tolerances, when the caller has computed it (an actor host, for a tick group at once); None:
    computed here."""
    # scalar comparisons, cheapest first: an actor host runs this at every robot's tick, where
    # numpy's any / array_equal on 2- and 3-vectors cost ~10 times as much
    if tolerances is None or previous is None or sample.step != previous.step + 1:
        return False
    action, before = sample.action, previous.action
    if len(action) != 2 or len(before) != 2 or action[0] or action[1] or before[0] or before[1]:
        return False
    state, earlier = sample.state, previous.state
    if len(state) != 3 or len(earlier) != 3 or state[0] != earlier[0] or state[1] != earlier[1]:
        return False
    if state[2] != earlier[2]:
        return False
    return arrival_update(False, state, tolerances) if inner is None else inner


def at_rest_rows(
    previous_steps: np.ndarray,
    previous: np.ndarray,
    steps: np.ndarray,
    values: np.ndarray,
    tolerances: ArrivalTolerances | None,
    inner: np.ndarray | None = None,
) -> np.ndarray:
    """:func:`at_rest` of many samples at once: row ``i`` is sample ``(steps[i], values[i])``
    after ``(previous_steps[i], previous[i])``, each ``values`` row ``(x, y, alpha, v, omega)``.
    The same comparisons: the step after, both actions exactly zero, the state exactly equal,
    then the inner tolerances (:func:`~common.math.arrival.arrival_masks`, :func:`arrival_update`'s
    test for many states; ``inner``: each row's, when the caller has computed them)."""
    if tolerances is None:
        return np.zeros(len(steps), dtype=bool)
    rest: np.ndarray = np.asarray(steps) == np.asarray(previous_steps) + 1
    # the state and the action exactly as before, and the action zero: both actions zero
    rest &= np.logical_and.reduce(values == previous, axis=1)
    rest &= np.logical_and.reduce(values[:, STATE_DIM:] == 0, axis=1)
    if inner is not None:
        rest &= inner
        return rest
    candidates = np.flatnonzero(rest)
    if candidates.size:
        rest[candidates] = arrival_masks(values[candidates, :STATE_DIM], tolerances)[0]
    return rest


class FitsDue:
    """What a robot's critic fits of the transitions its actor sends (:func:`at_rest`), as the
    actor sees it: ``newest``, the newest step sent that is fitted (-1: none), is the step fresh
    weights are trained on, so the weights' staleness is ``newest - trained_step`` (a robot at rest
    sends transitions nobody fits: its weights are as fresh as they can be)."""

    def __init__(self, tolerances: ArrivalTolerances | None) -> None:
        self.tolerances = tolerances
        self.reset()

    def reset(self) -> None:
        self.previous: Sample | None = None
        self.newest = -1
        self.resting = False  # the last sample sent was at rest

    def sent(self, sample: Sample, inner: bool | None = None) -> bool:
        """``sample`` goes to the critic: True when the critic fits on it (when one is due).
        ``inner``: as :func:`at_rest`'s."""
        self.resting = at_rest(self.previous, sample, self.tolerances, inner)
        self.previous = sample
        if not self.resting:
            self.newest = sample.step
        return not self.resting


def consecutive_pairs(steps: Sequence[int]) -> list[tuple[int, int]]:
    """Indices ``(a, b)`` into ``steps`` with ``steps[b] == steps[a] + 1`` and ``b == a + 1``.

    Only neighbours in the replay can pair, and only if no step is missing between them:
    a gap (lost or not yet received sample) is never bridged.
    """
    return [(a, a + 1) for a in range(len(steps) - 1) if steps[a + 1] == steps[a] + 1]


def lsq_linear(*args: Any, **kwargs: Any) -> Any:
    """scipy's ``lsq_linear``, imported on the first fit: scipy.optimize takes ~0.4 s of CPU to
    import, which every process that imports this module (the actor, the plant, the bridge)
    would pay at start-up without ever fitting. A process that will fit calls
    :func:`load_solver` before it is ready."""
    from scipy.optimize import lsq_linear as bvls

    return bvls(*args, **kwargs)


def load_solver() -> None:
    """Import scipy's BVLS now: the critic service pays the import (0.15-0.4 s of CPU, seconds on
    a loaded machine) before it declares itself alive, not in the first fit that needs BVLS, whose
    weights every actor would then wait for."""
    import scipy.optimize  # noqa: F401


KKT_TOLERANCE = 1e-10  # scipy's lsq_linear default ``tol``: the largest KKT violation accepted
ACTIVE_SET_STEPS = 3  # primal-dual active-set steps tried on a rejected guess before BVLS (fit_gram)


def bounded_lstsq(
    a: np.ndarray, b: np.ndarray, low: np.ndarray, high: np.ndarray, guess: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``min |a x - b|`` subject to ``low <= x <= high``: ``(x, on_bound)``.

    ``guess``: the ``on_bound`` of a previous, similar problem. If the minimum with that active
    set (:func:`solve_on_guess` on ``a^T a``, ``a^T b``) meets the KKT conditions (scipy's test and
    tolerance), that is the minimum: one linear solve. Otherwise scipy's BVLS (``lsq_linear``)
    solves it. Use a guess only for a strictly convex problem (full column rank, e.g. with a
    ridge): its minimum is unique, so both ways reach the same ``x`` (to rounding) and the guess
    changes the cost, never the answer.
    """
    n = a.shape[1]
    if guess is not None and guess.shape == (n,):
        blocks = [slice(0, n)]
        x, accepted, _ = solve_on_guess((a.T @ a)[None], (a.T @ b)[None], low[None], high[None], guess[None], blocks)
        if accepted[0, 0]:
            return x[0], guess.copy()
    solution = lsq_linear(a, b, bounds=(low, high), method="bvls", tol=KKT_TOLERANCE)
    return solution.x, np.asarray(solution.active_mask, dtype=float)


def solve_on_guess(
    gram: np.ndarray, linear: np.ndarray, low: np.ndarray, high: np.ndarray, guess: np.ndarray, blocks: Sequence[slice]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A stack of strictly convex box QPs ``min 1/2 x^T G x - g^T x``, ``low <= x <= high``, each
    solved on the assumption that ``guess`` (-1 on the low bound, +1 on the high, 0 free) is its
    active set: ``(x, accepted)``, ``accepted[i, j]`` when block ``blocks[j]`` of problem ``i``
    meets the KKT conditions (free weights within the bounds, gradient zero on them and pointing
    into the box on the bound ones, within :data:`KKT_TOLERANCE`), i.e. that block's ``x`` IS its
    minimum; and the gradient ``G x - g``. Blocks are independent problems (``G`` block-diagonal).
    Shapes: ``gram`` (B, n, n), the rest (B, n). One batched solve: the bound weights' rows and
    columns of ``G`` become the identity's, so the free weights solve their own system."""
    free = guess == 0
    fixed = np.where(guess < 0, low, np.where(guess > 0, high, 0.0))
    bound = ~free
    reduced = np.where(bound[:, :, None] | bound[:, None, :], 0.0, gram)
    diagonal = np.arange(gram.shape[-1])
    reduced[:, diagonal, diagonal] = np.where(bound, 1.0, gram[:, diagonal, diagonal])
    rhs = np.where(free, linear - (gram @ fixed[..., None])[..., 0], fixed)
    x = np.where(free, _solve_each(reduced, rhs), fixed)
    gradient = (gram @ x[..., None])[..., 0] - linear
    violation = np.where(free, np.abs(gradient), gradient * guess)  # > 0 on a bound: leaving it would lower the cost
    inside = bound | ((x >= low) & (x <= high))
    accepted = np.stack(
        [np.all(inside[:, b], axis=1) & (np.max(violation[:, b], axis=1) < KKT_TOLERANCE) for b in blocks], axis=1
    )
    return x, accepted, gradient


def _solve_each(matrices: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``matrices[i]^-1 rhs[i]`` for the stack in one call (numpy loops LAPACK over it: each the
    same bits as alone); a singular one (data too large for the ridge to matter) gives NaN and
    leaves the others be (its critic keeps its weights: DoubleCritic.accept)."""
    try:
        solution: np.ndarray = np.linalg.solve(matrices, rhs[..., None])[..., 0]
        return solution
    except np.linalg.LinAlgError:
        out = np.full(rhs.shape, np.nan)
        for i in range(len(matrices)):
            with contextlib.suppress(np.linalg.LinAlgError):
                out[i] = np.linalg.solve(matrices[i], rhs[i])
        return out


def next_guess(x: np.ndarray, gradient: np.ndarray, low: np.ndarray, high: np.ndarray, guess: np.ndarray) -> np.ndarray:
    """One primal-dual active-set step from :func:`solve_on_guess`'s answer: a free weight beyond
    a bound goes onto it, a bound weight whose gradient points out of the box is freed."""
    free = guess == 0
    leaving = ~free & (gradient * guess > KKT_TOLERANCE)
    return np.where(free, np.where(x < low, -1.0, np.where(x > high, 1.0, 0.0)), np.where(leaving, 0.0, guess))


def bvls_gram(gram: np.ndarray, linear: np.ndarray, low: np.ndarray, high: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One strictly convex box QP ``min 1/2 x^T G x - g^T x`` by scipy's BVLS: ``(x, on_bound)``.
    With ``G = R^T R`` (Cholesky), ``|R x - R^-T g|^2`` is the same objective up to a constant,
    an (n, n) least squares however many rows the data had."""
    upper = np.linalg.cholesky(gram).T
    solution = lsq_linear(upper, np.linalg.solve(upper.T, linear), bounds=(low, high), method="bvls", tol=KKT_TOLERANCE)
    return solution.x, np.asarray(solution.active_mask, dtype=float)


def fit_gram(
    now: np.ndarray,
    following: np.ndarray,
    costs: np.ndarray,
    previous: np.ndarray,
    blocks: Sequence[slice],
    discount: float,
    ridge: float,
    bounds: tuple[float, float] | None,
    guesses: Sequence[Sequence[np.ndarray | None]],
    pairs: Sequence[int],
) -> list[list[FitResult]]:
    """The TD fits of a stack of robots, each of one or more critics (``blocks``: each critic's
    columns), for a ridge ``> 0``: ``result[i][j]`` is robot ``i``'s critic ``j``
    (:func:`fit_stack`'s arrays as :class:`FitResult`)."""
    weights, residuals, on_bound = fit_stack(now, following, costs, previous, blocks, discount, ridge, bounds, guesses)
    return [
        [
            FitResult(weights[i, b], float(residuals[i, j]), pairs[i], on_bound[i, b] if bounds is not None else None)
            for j, b in enumerate(blocks)
        ]
        for i in range(len(weights))
    ]


def fit_stack(
    now: np.ndarray,
    following: np.ndarray,
    costs: np.ndarray,
    previous: np.ndarray,
    blocks: Sequence[slice],
    discount: float,
    ridge: float,
    bounds: tuple[float, float] | None,
    guesses: Sequence[Sequence[np.ndarray | None]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The TD fits of a stack of robots, each of one or more critics (``blocks``: each critic's
    columns), for a ridge ``> 0``: ``(weights (B, n), residuals (B, critics), on_bound (B, n))``.

    ``now``/``following`` (B, P, n): the designs, robots with fewer pairs padded with zero rows
    (zero ``costs`` too), which add nothing; ``previous`` (B, n): the weights; ``guesses[i][j]``:
    the last fit's ``on_bound`` of that critic (None: none yet, all weights are tried free). The
    same problem as :func:`td_fit` (``dw = w - w_prev`` with the ridge; with bounds, the step
    from the previous weights clipped into them), solved in the weights' space."""
    count, _, size = now.shape
    targets = costs[..., None] + discount * np.stack(
        [(following[:, :, b] @ previous[:, b, None])[..., 0] for b in blocks], axis=-1
    )  # (B, P, critics)
    if bounds is None:
        low, high = np.full((count, size), -np.inf), np.full((count, size), np.inf)
        base = previous
    else:
        low, high = np.full((count, size), float(bounds[0])), np.full((count, size), float(bounds[1]))
        base = np.clip(previous, low, high)  # previous weights outside new bounds: clipped first
    gram = np.zeros((count, size, size))
    linear = np.empty((count, size))
    for j, b in enumerate(blocks):
        design = now[:, :, b]
        gram[:, b, b] = np.swapaxes(design, 1, 2) @ design
        rhs = targets[..., j] - (design @ base[:, b, None])[..., 0]
        linear[:, b] = (np.swapaxes(design, 1, 2) @ rhs[..., None])[..., 0] - ridge * (base[:, b] - previous[:, b])
    diagonal = np.arange(size)
    gram[:, diagonal, diagonal] += ridge
    step_low, step_high = low - base, high - base
    guess = np.zeros((count, size))
    for i, row in enumerate(guesses):
        for b, g in zip(blocks, row, strict=True):
            if g is not None and bounds is not None and g.shape == (b.stop - b.start,):
                guess[i, b] = g
    step, accepted, gradient = solve_on_guess(gram, linear, step_low, step_high, guess, blocks)
    for _ in range(ACTIVE_SET_STEPS):  # the rejected guesses improved, all of them in one solve
        rejected = np.flatnonzero(~np.all(accepted, axis=1))
        if not rejected.size:
            break
        better = next_guess(
            step[rejected], gradient[rejected], step_low[rejected], step_high[rejected], guess[rejected]
        )
        changed = rejected[np.any(better != guess[rejected], axis=1)]
        if not changed.size:
            break
        guess[changed] = better[np.any(better != guess[rejected], axis=1)]
        step[changed], accepted[changed], gradient[changed] = solve_on_guess(
            gram[changed], linear[changed], step_low[changed], step_high[changed], guess[changed], blocks
        )
    on_bound = guess.copy()
    for i, j in zip(*np.nonzero(~accepted), strict=True):  # still not optimal: BVLS decides it
        b = blocks[j]
        try:
            step[i, b], on_bound[i, b] = bvls_gram(gram[i, b, b], linear[i, b], step_low[i, b], step_high[i, b])
        except (np.linalg.LinAlgError, ValueError):  # non-finite data: no fit (the caller keeps its weights)
            step[i, b] = np.nan
    weights = np.clip(base + step, low, high)
    residuals = np.stack(
        [
            np.sum(((now[:, :, b] @ weights[:, b, None])[..., 0] - targets[..., j]) ** 2, axis=1) / 2
            for j, b in enumerate(blocks)
        ],
        axis=1,
    )
    return weights, residuals, on_bound


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
    targets are ``c_j + discount * <previous_weights, phi(z_{j+1})>``. With a ridge: :func:`fit_gram`
    (``on_bound``: the last bounded fit's :attr:`FitResult.on_bound`, the guess of its active set,
    which makes this one cheaper and never changes the minimum). Without: the minimum-norm change
    by ``lstsq``, BVLS with bounds.
    """
    previous = np.asarray(previous_weights, dtype=float)
    a = np.atleast_2d(np.asarray(features_now, dtype=float))
    pairs = a.shape[0] if np.size(costs) else 0
    if pairs == 0:
        return FitResult(previous.copy(), 0.0, 0, on_bound)
    if ridge > 0:  # strictly convex: in the weights' space (fit_gram), as a stack of one
        size = previous.size
        return fit_gram(
            a[None],
            np.atleast_2d(np.asarray(features_next, dtype=float))[None],
            np.asarray(costs, dtype=float)[None],
            previous[None],
            [slice(0, size)],
            discount,
            ridge,
            bounds,
            [[on_bound]],
            [pairs],
        )[0][0]
    targets = np.asarray(costs, float) + discount * (np.asarray(features_next, float) @ previous)
    # Without a ridge: solve for dw = w - w_prev, A dw ~ targets - A w_prev (minimum norm dw).
    rhs = targets - a @ previous
    active = None
    if bounds is None:
        delta_w = np.linalg.lstsq(a, rhs, rcond=None)[0]
        weights = previous + delta_w
    else:
        low, high = bounds
        # The previous weights may sit outside new bounds: clip before measuring the change.
        base = np.clip(previous, low, high)
        step, active = bounded_lstsq(a, rhs - a @ (base - previous), low - base, high - base)
        weights = np.clip(base + step, low, high)
    errors = a @ weights - targets
    return FitResult(weights, 0.5 * float(errors @ errors), pairs, active)


class Replay:
    """The last ``capacity`` samples of ONE episode, kept in step order.

    Samples of its system's shape (a state of ``state_dim`` numbers, an action of ``action_dim``;
    the unicycle's 3 and 2 by default) are kept as ring arrays only: the steps, each sample's entry
    ``(step, s, u, cost)`` (the unicycle's ``(step, x, y, alpha, v, omega, cost)``: the
    checkpoint's row, :meth:`table` is two slices of the ring)
    and its TD row (``phi_Q`` then ``phi_V`` side by side, :func:`_phi_qv_rows`'s products, so
    the same bits), each row computed once when its sample enters. A fit builds its design
    from them (:func:`kept_designs`) with no Python loop over samples; :attr:`samples` and
    :attr:`newest` are read back from them (copies). A sample of another shape turns the replay
    into a list of its samples, with no rows (:attr:`kept` False: designs come from the
    samples) until it is cleared."""

    def __init__(self, capacity: int, state_dim: int = STATE_DIM, action_dim: int = ACTION_DIM) -> None:
        if capacity < 2:
            raise ValueError(f"replay size M must be >= 2 (one TD pair), got {capacity}")
        self.capacity = capacity
        self.state_dim, self.action_dim = state_dim, action_dim
        self.left, self.right = qv_products(state_dim, action_dim)  # a TD row: z[left] * z[right]
        self.steps = np.zeros(capacity, dtype=np.int64)  # ring slot -> step
        self.entries = np.zeros((capacity, 2 + state_dim + action_dim))  # ring slot -> (step, s, u, cost)
        self.values = self.entries[:, 1:-1]  # ring slot -> (s, u), a view
        self.costs = self.entries[:, -1]  # ring slot -> cost, a view
        self.rows = np.zeros((capacity, self.left.size))  # ring slot -> phi_Q, phi_V of its sample
        self.start = 0  # the ring slot of the oldest sample
        self.count = 0  # samples in the rings
        self.last = -1  # the newest sample's step (while one is held)
        self._others: deque[Sample] | None = None  # every sample, once one is of another shape
        self.kept = True  # every sample is in the rings, its TD row too (False: one of another shape)

    def __len__(self) -> int:
        return self.count if self._others is None else len(self._others)

    @property
    def max_pairs(self) -> int:
        """The most TD pairs its design can have: ``capacity - 1``."""
        return self.capacity - 1

    def _order(self) -> np.ndarray:
        """The ring slots of the samples held, oldest first."""
        return (self.start + np.arange(self.count)) % self.capacity

    @property
    def samples(self) -> list[Sample]:
        """The samples held, in step order (from the rings: copies)."""
        if self._others is not None:
            return list(self._others)
        order = self._order()
        steps, costs, values = self.steps[order].tolist(), self.costs[order].tolist(), self.values[order]
        n = self.state_dim
        return [Sample(step, values[i, :n], values[i, n:], costs[i]) for i, step in enumerate(steps)]

    @property
    def newest(self) -> Sample | None:
        """The sample of the highest step (None: empty)."""
        if self._others is not None:
            return self._others[-1] if self._others else None
        return self._sample((self.start + self.count - 1) % self.capacity) if self.count else None

    def _sample(self, slot: int) -> Sample:
        z = self.values[slot].copy()
        return Sample(int(self.steps[slot]), z[: self.state_dim], z[self.state_dim :], float(self.costs[slot]))

    def clear(self) -> None:
        self.start, self.count, self.last, self._others, self.kept = 0, 0, -1, None, True

    def add(self, sample: Sample) -> None:
        """Insert in step order; a duplicate step replaces nothing and raises."""
        state, action = np.asarray(sample.state, dtype=float), np.asarray(sample.action, dtype=float)
        if self._others is None and (state.shape != (self.state_dim,) or action.shape != (self.action_dim,)):
            self._others = deque(self.samples, maxlen=self.capacity)  # not its system's (s, u): no rows
            self.kept = False
        if self._others is not None:
            self._add_other(sample)
            return
        entry = np.concatenate([[sample.step], state, action, [sample.cost]])
        z = entry[1:-1]
        if self.count and sample.step <= self.last:
            order = self._order()
            steps = self.steps[order]
            if np.any(steps == sample.step):
                raise ValueError(f"step {sample.step} is already in the replay")
            # Late arrival (out of order): inserted where it belongs, then the oldest trimmed; the
            # rings rewritten from slot 0
            at = int(np.searchsorted(steps, sample.step))
            steps = np.insert(steps, at, sample.step)[-self.capacity :]
            entries = np.insert(self.entries[order], at, entry, axis=0)[-self.capacity :]
            self.start, self.count = 0, len(steps)
            self.steps[: self.count], self.entries[: self.count] = steps, entries
            np.multiply(entries[:, 1:-1][:, self.left], entries[:, 1:-1][:, self.right], out=self.rows[: self.count])
            return
        self.append(int(sample.step), entry, z[self.left] * z[self.right])

    def append(self, step: int, entry: np.ndarray, row: np.ndarray) -> None:
        """The sample of ``step``, after the newest held, into the next ring slot (full: the
        oldest's): its ``entry`` ``(step, x, y, alpha, v, omega, cost)`` and its TD ``row``, the
        products :func:`_phi_qv_rows` makes of its ``(x, y, alpha, v, omega)``
        (:func:`append_each` computes many at once). A step not after the newest, or a replay
        that keeps no rows: ValueError."""
        if not self.kept:
            raise ValueError("a replay of samples of another shape takes them one by one (Replay.add)")
        if self.count and step <= self.last:
            raise ValueError(f"step {step} is not after the replay's newest, {self.last}")
        slot = (self.start + self.count) % self.capacity
        if self.count == self.capacity:
            self.start = (self.start + 1) % self.capacity
        else:
            self.count += 1
        self.last = step
        self.steps[slot], self.entries[slot], self.rows[slot] = step, entry, row

    def _add_other(self, sample: Sample) -> None:
        others = self._others
        assert others is not None
        if others and sample.step <= others[-1].step:
            if any(s.step == sample.step for s in others):
                raise ValueError(f"step {sample.step} is already in the replay")
            # late arrival (out of order): inserted where it belongs, then the oldest trimmed
            others = self._others = deque(sorted([*others, sample], key=lambda s: s.step), maxlen=self.capacity)
        else:
            others.append(sample)
        self.last = others[-1].step

    def table(self) -> np.ndarray:
        """Its samples as rows ``(step, x, y, alpha, v, omega, cost)`` in step order, ``(n, 7)``
        (a checkpoint's replay): from the ring arrays, no Python loop over samples."""
        if self._others is not None:
            return np.array(
                [[s.step, *np.asarray(s.state, float), *np.asarray(s.action, float), s.cost] for s in self._others],
                dtype=float,
            ).reshape(-1, self.entries.shape[1])
        start, end = self.start, self.start + self.count
        if end <= self.capacity:
            return self.entries[start:end].copy()
        return np.concatenate((self.entries[start:], self.entries[: end - self.capacity]))

    def replays(self) -> list[Replay]:
        """Its streams as :func:`kept_designs` takes them: itself."""
        return [self]

    def design(self, features: Features) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(features_now, features_next, costs)`` over the consecutive pairs.

        ``features(states, actions)`` maps the replay's stacked states ``(n, 3)`` and actions
        ``(n, 2)`` to one feature row per sample (vectorized: one call per fit, not per sample).
        """
        return stream_design(self.sample_streams(), features)

    def sample_streams(self) -> list[Sequence[Sample]]:
        """Its samples as the streams of :func:`padded_designs`: one."""
        return [self.samples]


def append_each(replays: Sequence[Replay], steps: Sequence[int], costs: Sequence[float], values: np.ndarray) -> None:
    """One sample into each of ``replays``, in order, after its newest: ``replays[i]`` takes step
    ``steps[i]`` of ``values[i]`` = ``(x, y, alpha, v, omega)`` and ``costs[i]``, as
    :meth:`Replay.add` would; their TD rows are one product over all (elementwise: the same
    bits as each alone). What :meth:`Replay.append` refuses raises its ValueError (the replays
    before it have taken theirs)."""
    width = replays[0].values.shape[1] if replays else values.shape[-1]  # every replay of one system
    if len(replays) != len(steps) or len(steps) != len(costs) or values.shape != (len(steps), width):
        raise ValueError(f"{len(replays)} replays for {len(steps)} steps, {len(costs)} costs, values {values.shape}")
    if not replays:
        return
    entries = np.empty((len(steps), 2 + width))
    entries[:, 0], entries[:, 1:-1], entries[:, -1] = steps, values, costs
    rows = values[:, replays[0].left] * values[:, replays[0].right]
    for i, replay in enumerate(replays):
        replay.append(steps[i], entries[i], rows[i])


def newest_values(replays: Sequence[Replay]) -> tuple[np.ndarray, np.ndarray]:
    """Each replay's newest sample as ``(steps (R,), values (R, 5))``, ``(x, y, alpha, v, omega)``
    rows (every replay holds a sample and keeps rows: :attr:`Replay.kept`)."""
    steps = np.array([replay.last for replay in replays], dtype=np.int64)
    values = np.array([replay.values[(replay.start + replay.count - 1) % replay.capacity] for replay in replays])
    return steps, values.reshape(len(replays), replays[0].values.shape[1] if replays else STATE_DIM + ACTION_DIM)


def stream_design(streams: Iterable[Sequence[Sample]], features: Features) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The TD design of several sample streams, each in step order: ``(features_now,
    features_next, costs)`` over every stream's consecutive pairs, stream after stream.

    A pair joins two neighbours of ONE stream whose steps differ by one; the streams are laid end
    to end only after pairing, so no pair ever joins the last sample of one stream to the first of
    the next. The features are computed in one call over all samples.
    """
    now, following, costs, pairs = padded_designs([list(streams)], None, features)
    if not pairs[0]:
        return np.empty((0, 0)), np.empty((0, 0)), np.empty(0)
    return now[0], following[0], costs[0]


def padded_designs(
    designs: Sequence[Sequence[Sequence[Sample]]], rows: int | None, features: Features
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]]:
    """Several designs at once, each of its streams (as :func:`stream_design`), stacked:
    ``(now (B, rows, n), following, costs (B, rows), pairs)``, design ``i``'s ``pairs[i]`` rows
    first and zero rows after them (``rows``: None, the most pairs of any). The features of
    every sample of every design are computed in one call."""
    samples: list[Sample] = []
    now_index: list[int] = []
    pairs: list[int] = []
    for streams in designs:
        count = 0
        for stream in streams:
            items = list(stream)
            offset = len(samples)
            found = [offset + a for a, _ in consecutive_pairs([s.step for s in items])]
            now_index.extend(found)
            count += len(found)
            samples.extend(items)
        pairs.append(count)
    rows = max(pairs, default=0) if rows is None else rows
    if not now_index:
        return (
            np.zeros((len(designs), rows, 0)),
            np.zeros((len(designs), rows, 0)),
            np.zeros((len(designs), rows)),
            pairs,
        )
    phis = features(np.array([s.state for s in samples]), np.array([s.action for s in samples]))
    slots = np.concatenate([i * rows + np.arange(count) for i, count in enumerate(pairs)])
    index = np.array(now_index, dtype=np.intp)
    size = len(designs) * rows
    now, following, costs = np.zeros((size, phis.shape[1])), np.zeros((size, phis.shape[1])), np.zeros(size)
    now[slots], following[slots] = phis[index], phis[index + 1]
    costs[slots] = [samples[a].cost for a in now_index]
    shape = (len(designs), rows)
    return now.reshape(*shape, -1), following.reshape(*shape, -1), costs.reshape(shape), pairs


def kept_designs(
    designs: Sequence[Sequence[Replay]], rows: int | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]] | None:
    """:func:`padded_designs` of the TD rows (:func:`_phi_qv_rows`) from the replays' kept arrays:
    design ``i`` is the pairs of its streams ``designs[i]``, stream after stream, each in step
    order, then zero rows up to ``rows`` (None: the most pairs of any). The same arrays, bit for
    bit, with no loop over samples: every stream's ring read in step order at once, its pairs
    found by comparing neighbouring steps, their rows copied into place. None when a replay
    keeps no rows (:attr:`Replay.kept`) or the streams differ in capacity or system: then
    :func:`padded_designs` builds them from the samples."""
    streams = [replay for design in designs for replay in design]
    width = streams[0].rows.shape[1] if streams else 0  # every stream of one system
    if not streams or not all(
        r.kept and r.capacity == streams[0].capacity and r.rows.shape[1] == width for r in streams
    ):
        return None
    capacity = streams[0].capacity
    owner = np.repeat(np.arange(len(designs)), [len(design) for design in designs])
    position = np.arange(capacity)
    ring = (np.array([r.start for r in streams])[:, None] + position) % capacity  # (S, M): order -> slot
    held = position < np.array([len(r) for r in streams])[:, None]
    steps = np.take_along_axis(np.stack([r.steps for r in streams]), ring, axis=1)
    paired = held[:, 1:] & (steps[:, 1:] == steps[:, :-1] + 1)  # a gap, or the end, breaks a pair
    stream, first = np.nonzero(paired)  # stream after stream, each in step order
    design = owner[stream]
    pairs = np.bincount(design, minlength=len(designs))
    rows = int(pairs.max(initial=0)) if rows is None else rows
    offsets = np.concatenate([[0], np.cumsum(pairs)[:-1]])
    # every design row's source: its pair's sample in the streams' rings laid end to end, a zero
    # row (the last) for the padding; one gather per array, no temporaries
    target = design * rows + np.arange(stream.size) - offsets[design]
    now_source = np.full(len(designs) * rows, len(streams) * capacity, dtype=np.intp)
    following_source = now_source.copy()
    now_source[target] = stream * capacity + ring[stream, first]
    following_source[target] = stream * capacity + ring[stream, first + 1]
    features = np.concatenate([*(r.rows for r in streams), np.zeros((1, width))])
    now, following = np.take(features, now_source, axis=0), np.take(features, following_source, axis=0)
    costs = np.take(np.concatenate([*(r.costs for r in streams), np.zeros(1)]), now_source)
    shape = (len(designs), rows)
    return (
        now.reshape(*shape, width),
        following.reshape(*shape, width),
        costs.reshape(shape),
        pairs.tolist(),
    )


class PooledReplay:
    """The last ``capacity`` samples of each robot's episode: one :class:`Replay` per robot (its
    stream), one design over all of them (pairs only within a stream). Memory: at most
    ``capacity`` samples per robot held."""

    def __init__(self, capacity: int, state_dim: int = STATE_DIM, action_dim: int = ACTION_DIM) -> None:
        Replay(capacity, state_dim, action_dim)  # the same checks
        self.capacity = capacity
        self.state_dim, self.action_dim = state_dim, action_dim
        self.streams: dict[str, Replay] = {}

    def __len__(self) -> int:
        return sum(len(replay) for replay in self.streams.values())

    @property
    def max_pairs(self) -> int:
        """The most TD pairs its design can have: ``capacity - 1`` per stream."""
        return len(self.streams) * (self.capacity - 1)

    def stream(self, robot: str) -> Replay:
        """The robot's replay (created empty on first use)."""
        replay = self.streams.get(robot)
        if replay is None:
            replay = self.streams[robot] = Replay(self.capacity, self.state_dim, self.action_dim)
        return replay

    def restart(self, robot: str) -> Replay:
        """The robot starts a new episode: its stream starts empty (the others keep theirs)."""
        replay = self.streams[robot] = Replay(self.capacity, self.state_dim, self.action_dim)
        return replay

    def add(self, robot: str, sample: Sample) -> None:
        self.stream(robot).add(sample)

    def clear(self) -> None:
        self.streams.clear()

    def replays(self) -> list[Replay]:
        """Its streams as :func:`kept_designs` takes them: one per robot, in the order they joined."""
        return list(self.streams.values())

    def design(self, features: Features) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every stream's consecutive pairs, stacked (robots in the order they joined)."""
        return stream_design(self.sample_streams(), features)

    def sample_streams(self) -> list[Sequence[Sample]]:
        """Its samples as the streams of :func:`padded_designs`: one per robot."""
        return [replay.samples for replay in self.streams.values()]


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
        # the system's dimensions, told by the weights: phi_V(s) is s's quadratic, phi_Q(s, u) (s, u)'s
        self.state_dim = dim_of_features(self.v_weights.size)
        self.action_dim = dim_of_features(self.q_weights.size) - self.state_dim
        if self.action_dim < 1:
            raise ValueError(f"{self.q_weights.size} Q weights and {self.v_weights.size} V weights: no (s, u) has both")
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
        """One TD least-squares fit of both critics on the replay (Algorithm 1, line 6): a batch of
        one of :func:`update_many` (the same bits as in any batch)."""
        return update_many([self], [replay])[0]

    def fit_separately(self, now: np.ndarray, following: np.ndarray, costs: np.ndarray) -> CriticUpdate:
        """Both critics by :func:`td_fit`, one after the other (no ridge: the minimum-norm change)."""
        args = (self.discount, self.ridge, self.bounds)
        q = self.q_weights.size
        q_fit = td_fit(_columns(now, 0, q), _columns(following, 0, q), costs, self.q_weights, *args, self.q_on_bound)
        v_fit = td_fit(_columns(now, q), _columns(following, q), costs, self.v_weights, *args, self.v_on_bound)
        return self.accept(q_fit, v_fit)

    def accept(self, q_fit: FitResult, v_fit: FitResult) -> CriticUpdate:
        """Take the fits' weights and active sets -- never a non-finite fit (ill-conditioned
        data): then the previous weights stay."""
        return self.accept_checked(
            q_fit, v_fit, bool(np.all(np.isfinite(q_fit.weights))), bool(np.all(np.isfinite(v_fit.weights)))
        )

    def accept_checked(self, q_fit: FitResult, v_fit: FitResult, q_finite: bool, v_finite: bool) -> CriticUpdate:
        """:meth:`accept` with the fits' finiteness checked by the caller (a stack's at once)."""
        if q_finite:
            self.q_weights, self.q_on_bound = q_fit.weights, q_fit.on_bound
        if v_finite:
            self.v_weights, self.v_on_bound = v_fit.weights, v_fit.on_bound
        return CriticUpdate(q_fit, v_fit)


def update_many(
    critics: Sequence[DoubleCritic], replays: Sequence[Replay | PooledReplay], rebuild: bool = False
) -> list[CriticUpdate]:
    """One TD fit of both critics of each ``(critic, replay)``: ``critics[i].update(replays[i])``
    for every ``i``, in one stacked solve (:func:`fit_gram`) for all with a ridge (a fleet's
    critic fits every robot due in one batch: ~10x less CPU per fit at 100 robots than one at a
    time, ``srl bench critic``).

    One design per replay for both critics (phi_Q and phi_V side by side), padded with zero rows
    to the replay's :attr:`~Replay.max_pairs` whatever its own count: a robot's problem has the
    same shape, and its weights the same bits, in a batch of any size, and a pool of one robot
    is its per-robot learner bit for bit. The designs come from the replays' kept rows
    (:func:`kept_designs`); ``rebuild``: from their samples (:func:`padded_designs`, the same
    arrays: the reference the kept rows are tested against)."""
    results: list[CriticUpdate | None] = [None] * len(critics)
    # one stacked solve per shape: (beta, lambda, box, rows, phi_Q's and phi_V's lengths)
    groups: dict[tuple[float, float, tuple[float, float] | None, int, int, int], list[int]] = {}
    for i, (critic, replay) in enumerate(zip(critics, replays, strict=True)):
        if critic.ridge > 0:
            shape = (
                critic.discount,
                critic.ridge,
                critic.bounds,
                replay.max_pairs,
                critic.q_weights.size,
                critic.v_weights.size,
            )
            groups.setdefault(shape, []).append(i)
        else:
            kept = None if rebuild else kept_designs([replay.replays()], None)
            if kept is None:
                results[i] = critic.fit_separately(*replay.design(_phi_qv_rows))
            elif kept[3][0]:
                results[i] = critic.fit_separately(kept[0][0], kept[1][0], kept[2][0])
            else:  # no pair: the empty design of stream_design
                results[i] = critic.fit_separately(np.empty((0, 0)), np.empty((0, 0)), np.empty(0))
    for (discount, ridge, bounds, rows, q, _), group in groups.items():
        kept = None if rebuild else kept_designs([replays[i].replays() for i in group], rows)
        now, following, costs, pairs = kept or padded_designs(
            [replays[i].sample_streams() for i in group], rows, _phi_qv_rows
        )
        members = [k for k, count in enumerate(pairs) if count]
        for k in (k for k, count in enumerate(pairs) if not count):  # nothing to fit: the weights stay
            critic = critics[group[k]]
            results[group[k]] = critic.accept(
                FitResult(critic.q_weights.copy(), 0.0, 0, critic.q_on_bound),
                FitResult(critic.v_weights.copy(), 0.0, 0, critic.v_on_bound),
            )
        if not members:
            continue
        fitted = [critics[group[k]] for k in members]
        if len(members) < len(group):
            now, following, costs = now[members], following[members], costs[members]
        weights, residuals, on_bound = fit_stack(
            now,
            following,
            costs,
            np.array([np.concatenate([c.q_weights, c.v_weights]) for c in fitted]),
            [slice(0, q), slice(q, now.shape[2])],
            discount,
            ridge,
            bounds,
            [[c.q_on_bound, c.v_on_bound] for c in fitted],
        )
        finite = np.isfinite(weights)
        q_finite, v_finite = (
            finite[:, :q].all(axis=1).tolist(),
            finite[:, q:].all(axis=1).tolist(),
        )
        q_residuals, v_residuals = residuals[:, 0].tolist(), residuals[:, 1].tolist()
        for n, (k, critic) in enumerate(zip(members, fitted, strict=True)):
            q_bound, v_bound = (None, None) if bounds is None else (on_bound[n, :q], on_bound[n, q:])
            results[group[k]] = critic.accept_checked(
                FitResult(weights[n, :q], q_residuals[n], pairs[k], q_bound),
                FitResult(weights[n, q:], v_residuals[n], pairs[k], v_bound),
                q_finite[n],
                v_finite[n],
            )
    return [result for result in results if result is not None]


def _phi_qv_rows(states: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """phi_Q's columns, then phi_V's."""
    return np.hstack([phi_q_rows(states, actions), phi_v_rows(states)])


def _columns(rows: np.ndarray, start: int, stop: int | None = None) -> np.ndarray:
    """Columns ``start:stop`` as their own contiguous array (the fit's products then run as on a
    design built alone); an empty design stays empty."""
    return np.ascontiguousarray(rows[:, start:stop]) if rows.size else rows


class PooledLearner:
    """ONE :class:`DoubleCritic` learning from a fleet's transitions (the pooled critic, docs/fleets.md).

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
        self.replay = PooledReplay(capacity, critic.state_dim, critic.action_dim)
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
