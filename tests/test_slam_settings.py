"""The `slam` operator's settings (rover.operators.slam.settings): the rules between fields."""

from __future__ import annotations

import pytest

from rover.operators.slam.settings import WindowSettings
from rover.pipeline.params import ParamValueError


def test_the_source_floor_must_leave_room_to_be_localized():
    """A tag's published covariance has source_std_m in every direction, so at observable_std_m or
    more no tag could ever be localized: refused, naming both."""
    assert WindowSettings(source_std_m=0.0).source_std_m == 0.0
    assert WindowSettings(source_std_m=0.49).source_std_m == 0.49
    with pytest.raises(ParamValueError, match=r"source_std_m: 0\.5 m is not below observable_std_m \(0\.5 m\)"):
        WindowSettings(source_std_m=0.5)
    with pytest.raises(ParamValueError, match="source_std_m"):
        WindowSettings(source_std_m=0.3, observable_std_m=0.2)
