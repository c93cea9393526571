"""The loop's moves (solver/engine/recentring.py) against moves between blocks: a check shared by the
tests of a following ball (tests/solver/engine/test_follow.py) and of one in a moving frame
(tests/solver/engine/test_frame.py)."""

from __future__ import annotations

import numpy as np
from yauyau.solver.filtering import concat_results


def assert_loop_moves_as_blocks(flt, sim, outlier: float = 5.0):
    """Filter ``sim``'s rows (one missing, one an outlier of ``outlier`` in the first component) with
    the loop's moves and again block by block, moving between blocks where the loop moved."""
    rows = sim.rows.copy()
    rows[50] = np.nan
    rows[230, 0] += outlier
    start_state = flt.initial_state()
    state, result = flt.run_arrays(start_state, rows)
    moves = np.flatnonzero(result.recentred)
    assert flt.moves_in_loop and len(moves) >= 3 and bool(result.gated[230]) and not result.degenerate.any()
    replay, first, parts = start_state, 0, []
    for k in [*moves.tolist(), len(rows) - 1]:
        if k < first:
            continue
        center = replay.center  # a block from there (the centred engine, or the frame's)
        replay, part = flt.runner(center).run_arrays(replay, rows[first:k + 1])
        replay = flt._placed(replay, center)
        parts.append(part)
        if result.recentred[k]:
            replay = flt.recentre(replay, result.center[k])
        first = k + 1
    blocks = concat_results(parts)
    np.testing.assert_allclose(result.mean, blocks.mean, rtol=0, atol=1e-9)
    np.testing.assert_allclose(result.cov, blocks.cov, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(result.loglik, blocks.loglik, rtol=1e-11, atol=1e-9)
    np.testing.assert_array_equal(result.gated, blocks.gated)
    np.testing.assert_allclose(state.center, replay.center, rtol=0, atol=1e-12)
    np.testing.assert_allclose(state.coefficients, replay.coefficients, rtol=1e-9,
                               atol=1e-12 * np.abs(replay.coefficients).max())
