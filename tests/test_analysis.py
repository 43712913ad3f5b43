"""The behavioural analysis (:mod:`ccrjax.viz.analysis`) on hand-built episodes: arrival order,
closest approach, and the followers' closest approach counting only robots that succeeded."""

from __future__ import annotations

import numpy as np
import pytest

from ccrjax.viz.analysis import arrival_analysis, followers_closest


def one_episode(tracks: list[list[float]], success: list[bool]) -> dict[str, np.ndarray]:
    """One run, one episode: robot ``i`` moves along y = 0 through the x values
    ``tracks[i]``; the obstacle is the square of half-size 0.5 at the origin."""
    position = np.array(tracks, np.float64).T  # [T + 1, N]
    position = np.stack([position, np.zeros_like(position)], axis=2)  # [T + 1, N, 2]
    return {
        "position": position[None, ..., None],  # [G=1, T + 1, N, 2, E=1]
        "hazard_centre": np.zeros((1, 2, 1)),
        "hazard_half_extent": np.full((1, 2, 1), 0.5),
        "success": np.array(success)[None, :, None],  # [G, N, E]
    }


def test_arrival_order_closest_approach_and_successful_followers():
    # Robot 0 arrives second (touches at step 2), robot 1 first (step 1), robot 2 never
    # comes within reach (0.3); surface distances are |x| - 0.5.
    episodes = one_episode([[-3.0, -2.0, -0.5, -2.0],
                            [-3.0, -0.6, -1.0, -1.5],
                            [-3.0, -2.5, -2.0, -1.5]],
                           success=[True, False, True])
    analysis = arrival_analysis(episodes, reach=0.3)
    np.testing.assert_allclose(analysis["closest"][0, 0], [0.1, 0.0, 1.0])  # by rank
    np.testing.assert_array_equal(analysis["succeeded"][0, 0], [False, True, True])
    # Followers (ranks 2 and 3) that succeeded: robots 0 and 2, closest 0.0 and 1.0.
    assert followers_closest(analysis)[0] == pytest.approx(0.5)
    # No successful follower: NaN, never a number that flatters a team that gave up.
    episodes["success"][:] = False
    assert np.isnan(followers_closest(arrival_analysis(episodes, reach=0.3))[0])
