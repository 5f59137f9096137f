"""The boundary-condition program: piecewise-constant rigid motion of the Dirichlet set."""

import numpy as np

from latentsim.scene import bc_parameters, dirichlet_trajectory


def test_constant_translation_moves_by_v_dt_per_frame():
    seq = {"segments": [{"start": 0, "velocity": [0.3, 0.0, 0.0]}]}
    p = bc_parameters(seq, 11)
    assert np.all(p[0] == 0)
    assert np.allclose(p[1:, :3], [0.3, 0, 0]) and np.all(p[:, 3:] == 0)
    rest = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    xD = dirichlet_trajectory(rest, p, 0.1)
    assert np.allclose(xD[10] - rest, [0.3 * 0.1 * 10, 0, 0])


def test_reverse_every_flips_sign_and_returns_to_start():
    seq = {"reverse_every": 5, "segments": [{"velocity": [1.0, 0, 0]}]}
    p = bc_parameters(seq, 11)
    assert np.allclose(p[1:6, 0], 1.0) and np.allclose(p[6:11, 0], -1.0)
    xD = dirichlet_trajectory(np.zeros((1, 3)), p, 0.1)
    assert np.allclose(xD[5, 0, 0], 0.5) and np.allclose(xD[10], 0.0)


def test_segments_switch_at_their_start_frame():
    seq = {"segments": [{"start": 0, "velocity": [1.0, 0, 0]}, {"start": 4, "velocity": [0, 2.0, 0]}]}
    p = bc_parameters(seq, 6)
    assert np.allclose(p[3, :3], [1, 0, 0]) and np.allclose(p[4, :3], [0, 2, 0])


def test_rotation_is_rigid_and_about_the_centroid():
    rest = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 0, 1.0], [0, 0, -1.0]])
    w = np.pi / 2  # a quarter turn per second about +y
    p = bc_parameters({"segments": [{"angular_velocity": [0, w, 0]}]}, 11)
    xD = dirichlet_trajectory(rest, p, 0.1)
    # after 1 s a quarter turn: (1,0,0) -> (0,0,-1) for a rotation about +y
    assert np.allclose(xD[10][0], [0, 0, -1.0], atol=1e-12)
    for t in range(11):
        d = np.linalg.norm(xD[t][:, None] - xD[t][None], axis=-1)
        assert np.allclose(d, np.linalg.norm(rest[:, None] - rest[None], axis=-1))
        assert np.allclose(xD[t].mean(0), 0.0)
