import imageio.v2 as iio
import numpy as np
import pytest

from evchain.core.chain import run_pipeline
from evchain.core.config import pipeline_from_text
from evchain.core.packets import Geometry
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


def write_video(tmp_path, name, fps, geometry=None, frame_us=20_000, scale=1):
    packets, truth = expansion_stream(n_packets=4, packet_us=25_000, foe_series=True,
                                      **({"geometry": geometry} if geometry else {}))
    ctx = make_context(packets[0].geometry, truth, tmp_path)
    f = Video()
    f.setup(Video.Params(path=name, frame_us=frame_us, fps=fps, scale=scale), ctx)
    run_filter(f, packets)
    f.close()
    return tmp_path / name, ctx


def gif_delays_ms(path):
    from PIL import Image

    with Image.open(path) as im:
        delays = []
        for i in range(im.n_frames):
            im.seek(i)
            delays.append(im.info["duration"])
    return delays


@pytest.mark.parametrize("fps, delay_ms, warns", [(25, 40, False), (20, 50, False),
                                                  (30, 30, True)])
def test_gif_frame_delay(tmp_path, fps, delay_ms, warns):
    """The written GIF holds one frame per 20 ms of stream, each shown for 1/fps (in the GIF's
    whole hundredths of a second)."""
    path, ctx = write_video(tmp_path, "v.gif", fps)
    assert gif_delays_ms(path) == [delay_ms] * 5
    assert any("33.33" in w for w in ctx.warnings) == warns


def test_gif_faster_than_50_fps_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="GIF plays at most 50 frames per second"):
        Video().setup(Video.Params(path="x.gif", fps=100), make_context(None, None, tmp_path))


@pytest.mark.parametrize("geometry", [None, Geometry(63, 47)])
def test_mp4_frames_and_timing(tmp_path, geometry):
    """MP4 is written (an atomic .partial name that ffmpeg cannot guess a format from) and reads
    back with one frame per 20 ms of stream at exactly the requested fps; odd sizes are padded
    to even ones."""
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    path, _ = write_video(tmp_path, "v.mp4", 12.5, geometry=geometry)
    assert path.exists() and not (tmp_path / "v.mp4.partial").exists()
    frames = imageio_ffmpeg.read_frames(str(path))
    meta = next(frames)
    images = [np.frombuffer(b, np.uint8).reshape(meta["size"][1], meta["size"][0], 3)
              for b in frames]
    assert len(images) == 5
    assert meta["fps"] == 12.5
    assert meta["duration"] == pytest.approx(5 / 12.5, abs=0.01)
    w, h = (128, 96) if geometry is None else (64, 48)
    assert tuple(meta["size"]) == (w, h)
    if geometry is None:  # the estimated FOE's yellow cross at (70, 40), blurred by H.264's
        r, g, b = images[0][40, 70].astype(int)  # half-resolution colour: still yellow
        assert r > 180 and g > 180 and b < 130


def test_mp4_without_imageio_ffmpeg_is_a_config_error(tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)
    packets, truth = expansion_stream(n_packets=1, foe_series=True)
    f = Video()
    f.setup(Video.Params(path="v.mp4"), make_context(packets[0].geometry, truth, tmp_path))
    with pytest.raises(ConfigError, match=r"pip install 'evchain\[video\]'"):
        run_filter(f, packets)
    f.close()
