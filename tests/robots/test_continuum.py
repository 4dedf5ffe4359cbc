import pickle

import pytest
import torch

from pipeline.errors import ConfigError
from pipeline.robots import ContinuumRobot


def robot(**kw):
    args = dict(length_m=0.2, base_radius_m=0.015, tip_radius_m=0.006)
    args.update(kw)
    return ContinuumRobot(**args)


def test_defaults_and_helpers():
    r = robot()
    assert r.base_point_cam_m is None and r.base_direction_cam is None
    radii = r.initial_radii_m(dtype=torch.float64)
    assert radii.shape == (100,) and radii[0] == pytest.approx(0.015) and radii[-1] == pytest.approx(0.006)
    assert r.faces().shape == (2 * 40 * 99 + 80, 3)
    assert pickle.loads(pickle.dumps(r)) == r


def test_known_base_is_normalised_to_tuples():
    r = robot(base_point_cam_m=[0, 0.1, 0.4], base_direction_cam=(0.0, 0.6, 0.8))
    assert r.base_point_cam_m == (0.0, 0.1, 0.4)
    assert r.base_direction_cam == (0.0, 0.6, 0.8)


@pytest.mark.parametrize(
    "kw, message",
    [
        (dict(base_radius_m=0.0), "base radius must be > 0 m, got 0.0"),
        (dict(tip_radius_m=-1.0), "tip radius must be > 0 m, got -1.0"),
        (dict(length_m=float("nan")), "length must be > 0 m"),
        (dict(frame_method="bishop"), "'rmf', 'frenet'"),
        (dict(base_direction_cam=(0, 0, 2)), "unit vector"),
        (dict(base_point_cam_m=(0, 0)), "three numbers"),
    ],
)
def test_validation(kw, message):
    with pytest.raises(ConfigError, match=message):
        robot(**kw)


def test_frozen():
    with pytest.raises(AttributeError):
        robot().length_m = 1.0
