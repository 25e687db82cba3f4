"""How the experiment judges a run (the report and the figures use the same numbers)."""

from __future__ import annotations

PARK_TOLERANCE_M = 0.25  # "parked": final distance to the target at most this (as tests/test_closed_loop.py)
# A ratio within this of 100 % is a tie, not a win: the solver's tolerance alone moves J that much
# (an agent whose objective equals MPC's up to scale lands 1e-4 % off 100 %, either side).
TIE_PERCENT = 0.1
