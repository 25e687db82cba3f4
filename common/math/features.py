"""Stage cost and the critics' quadratic features, in the paper's notation (section III).

``phi(z)`` concatenates the entries of ``z z^T`` diagonal by diagonal: the main diagonal
first (``i - j = 0``), then ``i - j = 1`` and so on, each diagonal in increasing row ``i``.
For ``z = (s, u)`` in R^5 that is 15 features (``phi_Q``); for ``z = s`` in R^3, 6 (``phi_V``).
The functions are dimension-generic and accept numpy arrays or CasADi symbols.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

from common.math.dynamics import ACTION_DIM, STATE_DIM, is_symbolic


def feature_count(dim: int) -> int:
    """Number of products ``z_i z_j`` with ``i >= j`` of a vector of length ``dim``."""
    return dim * (dim + 1) // 2


def dim_of_features(count: int) -> int:
    """The ``dim`` with ``feature_count(dim) == count`` (a critic's weights tell its vector's
    length); ValueError when ``count`` is no such number (1, 3, 6, 10, 15, 21, ...)."""
    dim = round((math.isqrt(8 * count + 1) - 1) / 2) if count > 0 else 0
    if dim < 1 or feature_count(dim) != count:
        raise ValueError(f"{count} weights are no quadratic's (1, 3, 6, 10, 15, 21, ... for a vector of 1, 2, 3, ...)")
    return dim


Q_FEATURES = feature_count(STATE_DIM + ACTION_DIM)  # phi_Q(s, u): 15 for the unicycle
V_FEATURES = feature_count(STATE_DIM)  # phi_V(s): 6


def feature_index_pairs(dim: int) -> list[tuple[int, int]]:
    """``(i, j)`` of each feature, in the paper's order (diagonal ``k = i - j`` outermost)."""
    return [(i, i - k) for k in range(dim) for i in range(k, dim)]


def quadratic_features(z: Any) -> Any:
    """``concat_{k=0}^{n-1} concat_{i-j=k} (z z^T)_{ij}`` for numpy or CasADi ``z``."""
    dim = int(z.shape[0])
    products = [z[i] * z[j] for i, j in feature_index_pairs(dim)]
    if is_symbolic(z):
        import casadi as ca

        return ca.vertcat(*products)
    return np.array(products, dtype=float)


def quadratic_feature_rows(z: np.ndarray) -> np.ndarray:
    """:func:`quadratic_features` of every row of ``z`` (numpy, shape ``(n, dim)``) at once.

    Row ``k`` equals ``quadratic_features(z[k])`` bit for bit (the same products, vectorized).
    """
    z = np.asarray(z, dtype=float)
    rows, cols = _index_arrays(z.shape[1])
    features: np.ndarray = z[:, rows] * z[:, cols]
    return features


@functools.cache
def _index_arrays(dim: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`feature_index_pairs` as two index arrays (built once per dimension)."""
    pairs = feature_index_pairs(dim)
    return np.array([i for i, _ in pairs], dtype=np.intp), np.array([j for _, j in pairs], dtype=np.intp)


def phi_q_rows(states: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """``phi_Q`` of many ``(s, u)`` at once: shape ``(n, 15)``."""
    return quadratic_feature_rows(np.hstack([np.asarray(states, float), np.asarray(actions, float)]))


def phi_v_rows(states: np.ndarray) -> np.ndarray:
    """``phi_V`` of many states at once: shape ``(n, 6)``."""
    return quadratic_feature_rows(states)


def phi_q(state: Any, action: Any) -> Any:
    """Q-critic features ``phi_Q(s, u)`` (15 for the unicycle)."""
    if is_symbolic(state) or is_symbolic(action):
        import casadi as ca

        return quadratic_features(ca.vertcat(state, action))
    return quadratic_features(np.concatenate([np.asarray(state, float), np.asarray(action, float)]))


def phi_v(state: Any) -> Any:
    """Value-critic features ``phi_V(s)`` (6 for the unicycle)."""
    return quadratic_features(state if is_symbolic(state) else np.asarray(state, float))


def stage_cost(state: Any, action: Any, cost_diag: Any) -> Any:
    """``r(s, u) = chi^T R chi`` with ``chi = (s, u)`` and ``R = diag(cost_diag)``."""
    n = int(state.shape[0])
    total = 0.0
    for i in range(n):
        total = total + cost_diag[i] * state[i] * state[i]
    for i in range(int(action.shape[0])):
        total = total + cost_diag[n + i] * action[i] * action[i]
    return total


def stage_cost_rows(states: np.ndarray, actions: np.ndarray, cost_diag: Any) -> np.ndarray:
    """:func:`stage_cost` of many ``(s, u)`` at once (rows), bit for bit: the same products
    summed in the same order."""
    states, actions = np.asarray(states, dtype=float), np.asarray(actions, dtype=float)
    n = states.shape[1]
    z = np.hstack([states, actions])
    terms = np.asarray(cost_diag[: z.shape[1]], dtype=float) * z * z  # (c_i z_i) z_i, as stage_cost's
    total: np.ndarray = np.zeros(states.shape[0])
    for i in range(n + actions.shape[1]):  # summed from 0, in stage_cost's order
        total += terms[:, i]
    return total


def quadratic_weights_for_diag(diag: Any) -> np.ndarray:
    """Weights ``w`` with ``<w, phi(z)> = z^T diag(diag) z`` (main-diagonal features only)."""
    diag = np.asarray(diag, dtype=float)
    weights = np.zeros(feature_count(diag.size))
    weights[: diag.size] = diag
    return weights
