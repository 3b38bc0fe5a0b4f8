import imageio.v2 as iio
import numpy as np
import pytest

from evchain.core.chain import run_pipeline
from evchain.core.config import pipeline_from_text
from evchain.core.registry import make_registry
from evchain.errors import ConfigError, FilterError
from evchain.filters.video import Video
from evchain.report.render import colour_wheel, direction_colours
from evchain.testing.contract import make_context, run_filter
from evchain.testing.synthetic import expansion_stream


def test_direction_colours_follow_angle():
    rgb = direction_colours(np.array([1.0, 0.0, -1.0]), np.array([0.0, 1.0, 0.0]))
    assert tuple(rgb[0]) == (255, 0, 0)  # right: red
    assert rgb[2][2] > 200 and rgb[2][0] == 0  # left: cyan
    assert colour_wheel(11).shape == (11, 11, 3)


def test_gif_of_flow_with_overlays(tmp_path):
    packets, truth = expansion_stream(n_packets=4, packet_us=25_000, foe_series=True)
    f = Video()
    f.setup(Video.Params(path="flow.gif", frame_us=20_000, scale=1),
            make_context(packets[0].geometry, truth, tmp_path))
    run_filter(f, packets)
    f.close()
    frames = iio.mimread(tmp_path / "flow.gif")
    assert len(frames) == 5  # 100 ms in frames of 20 ms
    first = np.asarray(frames[0])[..., :3]
    assert first.shape == (96, 128, 3)
    assert (first[40, 70] == (255, 220, 0)).all()  # estimated FOE (yellow) over the true one
    assert not (tmp_path / "flow.gif.partial").exists()


def test_failed_run_leaves_only_partial(tmp_path):
    packets, truth = expansion_stream(n_packets=4, packet_us=25_000, foe_series=True)
    (tmp_path / "flow.gif").write_bytes(b"stale output of an earlier run")
    f = Video()
    f.setup(Video.Params(path="flow.gif", frame_us=20_000, scale=1),
            make_context(packets[0].geometry, truth, tmp_path))
    for p in packets[:3]:  # frames are written, then the run fails: no flush
        f.process(p)
    f.close()
    assert not (tmp_path / "flow.gif").exists()
    assert (tmp_path / "flow.gif.partial").read_bytes()[:6] == b"GIF89a"


def test_bad_suffix_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="must end in .gif or .mp4"):
        Video().setup(Video.Params(path="x.avi"), make_context(None, None, tmp_path))


def test_failed_run_leaves_no_video(tmp_path):
    registry = make_registry()
    (tmp_path / "x.h5").write_text("not HDF5")  # the source fails in setup
    text = f"chain:\n  - use: hdf5\n    path: {tmp_path / 'x.h5'}\n  - use: video\n"
    with pytest.raises(FilterError):
        run_pipeline(pipeline_from_text(text, "p.yaml", registry), registry, tmp_path)
    assert not (tmp_path / "events.gif").exists()
