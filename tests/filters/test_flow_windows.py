"""The window settings both event flows (LK and plane fitting) derive from the camera."""

from __future__ import annotations

import pytest

from evchain.core.camera_scale import REFERENCE_FOCAL_PX
from evchain.core.filter import Context
from evchain.core.packets import Geometry
from evchain.errors import ConfigError
from evchain.filters.lk_flow import LKFlow
from evchain.filters.plane_flow import PlaneFlow


@pytest.mark.parametrize("flow", [LKFlow, PlaneFlow])
@pytest.mark.parametrize("bad, says", [
    (dict(max_window_us=80_000), "must exceed window_us"),
    (dict(min_window_us=80_000), "must be shorter than window_us"),
    (dict(window_us=700_000), "must exceed window_us"),
])
def test_adaptive_window_bad_settings_on_the_camera_are_refused(flow, bad, says):
    """Settings that are valid alone fail once the null ones are derived from the camera (80 ms
    and the longest window on the reference camera), with the camera named."""
    f = flow()
    f.setup(flow.Params(**bad), Context())
    with pytest.raises(ConfigError, match=says + ".* on this 320x240 camera"):
        f.kernel_params(Geometry(320, 240, f=REFERENCE_FOCAL_PX))
