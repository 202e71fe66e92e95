"""The ground floor's rotation maths (midas_cli/geometry.py) agrees with itself in every direction:
angles, matrices and quaternions describe the same rotation whichever way they are converted."""

from __future__ import annotations

import numpy as np
import pytest

from midas_cli.geometry import (angles_from_matrices, apply_rigid, apply_similarity, matrices_from_angles,
                                matrices_from_quaternions, quaternions_from_angles, quaternions_from_matrices,
                                wrap_degrees)

RNG = np.random.default_rng(7)
# azimuth and roll anywhere, elevation inside (-90, 90) where the Z-Y-X angles are unique
ANGLES = np.column_stack([RNG.uniform(-180, 180, 500), RNG.uniform(-89, 89, 500), RNG.uniform(-180, 180, 500)])


def test_matrices_are_proper_rotations_in_the_trakstar_order() -> None:
    r = matrices_from_angles(ANGLES)
    assert np.allclose(r @ r.transpose(0, 2, 1), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(r), 1.0)
    # azimuth alone turns x towards y (about z); elevation alone turns x towards -z (about y)
    assert np.allclose(matrices_from_angles(np.array([[90.0, 0, 0]]))[0] @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(matrices_from_angles(np.array([[0, 90.0, 0]]))[0] @ [1, 0, 0], [0, 0, -1])


def test_angles_round_trip_through_matrices() -> None:
    back = angles_from_matrices(matrices_from_angles(ANGLES))
    assert np.allclose(back, ANGLES, atol=1e-9)
    wrapped = angles_from_matrices(matrices_from_angles(np.array([[180.0, 0.0, 180.0]])), wrap=True)
    assert wrapped[0, 0] == -180.0 and wrapped[0, 2] == -180.0  # the trakSTAR's range is [-180, 180)


def test_quaternions_from_angles_and_from_matrices_agree_and_invert() -> None:
    direct = quaternions_from_angles(ANGLES)
    via = quaternions_from_matrices(matrices_from_angles(ANGLES))
    sign = np.sign((direct * via).sum(axis=1))[:, None]  # q and -q are one rotation
    assert np.allclose(direct * sign, via, atol=1e-9)
    assert np.allclose(np.linalg.norm(via, axis=1), 1.0) and np.all(via[:, 3] >= 0)
    assert np.allclose(matrices_from_quaternions(direct), matrices_from_angles(ANGLES), atol=1e-9)


@pytest.mark.parametrize("angle", [-540.0, -180.0, -0.5, 0.0, 179.999, 180.0, 359.0, 720.0])
def test_wrap_degrees_lands_in_the_half_open_range(angle: float) -> None:
    wrapped = float(wrap_degrees(np.array([angle]))[0])
    assert -180.0 <= wrapped < 180.0 and np.isclose(np.cos(np.radians(wrapped)), np.cos(np.radians(angle)))


def test_rigid_and_similarity_transforms_agree() -> None:
    rotation, translation = matrices_from_angles(ANGLES[:1])[0], np.array([1.0, -2.0, 3.0])
    points = RNG.normal(size=(50, 3))
    assert np.allclose(apply_rigid(rotation, translation, points), apply_similarity(rotation, translation, 1.0, points))
