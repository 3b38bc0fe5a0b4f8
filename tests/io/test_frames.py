"""Source ``frames``: image folders, .npz/.npy arrays, luminance conversion, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from evchain.core.filter import Context
from evchain.errors import ConfigError, DataError
from evchain.io.frames import FramesSource, srgb_to_linear
from evchain.testing.contract import check_source


def read_all(params, tmp_path):
    f = FramesSource()
    f.setup(FramesSource.Params(**params), Context(out_dir=tmp_path))
    try:
        return list(f.packets()), f
    finally:
        f.close()


def test_npz_with_timestamps_and_contract(tmp_path):
    rng = np.random.default_rng(0)
    frames = rng.random((10, 6, 8)).astype(np.float32)
    t = np.arange(10, dtype=np.int64) * 250 + 1000
    np.savez(tmp_path / "a.npz", frames=frames, t=t)
    packets = check_source(FramesSource, {"path": str(tmp_path / "a.npz"),
                                          "frames_per_packet": 3})
    assert [len(p.t) for p in packets] == [3, 3, 3, 1]
    allf = np.concatenate([p.frames for p in packets])
    np.testing.assert_array_equal(allf, frames)            # float arrays: linear, as is
    assert packets[0].t_start == 1000 and packets[1].t_start == 1750
    assert packets[-1].t_end == int(t[-1]) + 1


def test_npy_uint16_rgb_with_fps(tmp_path):
    rgb = np.zeros((4, 3, 5, 3), np.uint16)
    rgb[..., 0] = 65535                      # pure red
    rgb[1, ..., :] = 65535                   # white
    np.save(tmp_path / "b.npy", rgb)
    packets, _ = read_all({"path": str(tmp_path / "b.npy"), "fps": 1000.0}, tmp_path)
    f = packets[0].frames
    np.testing.assert_allclose(f[0], 0.2126, rtol=1e-6)   # Rec. 709 weight of red
    np.testing.assert_allclose(f[1], 1.0, rtol=1e-6)
    np.testing.assert_array_equal(packets[0].t, [0, 1000, 2000, 3000])


def test_image_folder_srgb(tmp_path):
    import imageio.v3 as iio

    for i in range(5):
        img = np.full((4, 6), 50 * i, np.uint8)
        iio.imwrite(tmp_path / f"f{i:03d}.png", img)
    (tmp_path / "notes.txt").write_text("ignored")
    packets, _ = read_all({"path": str(tmp_path), "fps": 100.0, "frames_per_packet": 2},
                          tmp_path)
    got = np.concatenate([p.frames for p in packets])[:, 0, 0]
    np.testing.assert_allclose(got, srgb_to_linear(np.arange(5) * 50 / 255.0), rtol=1e-6)
    lin, _ = read_all({"path": str(tmp_path), "fps": 100.0, "encoding": "linear"}, tmp_path)
    np.testing.assert_allclose(lin[0].frames[:, 0, 0], np.arange(5) * 50 / 255.0, rtol=1e-6)
    assert packets[1].t[0] == 20_000


def test_timestamps_file(tmp_path):
    np.save(tmp_path / "c.npy", np.ones((3, 2, 2), np.float32))
    (tmp_path / "t.txt").write_text("5\n17\n40\n")
    packets, _ = read_all({"path": str(tmp_path / "c.npy"),
                           "timestamps_path": str(tmp_path / "t.txt")}, tmp_path)
    np.testing.assert_array_equal(packets[0].t, [5, 17, 40])


@pytest.mark.parametrize("bad", ["nan", "negative", "decreasing", "shape", "no_fps",
                                 "ndim", "count"])
def test_bad_input_names_the_place(tmp_path, bad):
    frames = np.ones((4, 3, 3), np.float32)
    t = np.array([0, 10, 20, 30])
    params = {"path": str(tmp_path / "x.npz")}
    err, pat = DataError, ""
    if bad == "nan":
        frames[2, 1, 1] = np.nan
        pat = r"x.npz frame 2: value not finite .*y=1, x=1"
    elif bad == "negative":
        frames[3, 0, 2] = -1
        pat = r"frame 3: negative value at \(y=0, x=2\)"
    elif bad == "decreasing":
        t = np.array([0, 10, 10, 30])
        pat = r"x.npz: timestamps must increase; frame 2 at 10 us follows 10 us"
    elif bad == "shape":
        frames = np.ones((4, 3, 3, 7), np.float32)
        pat = "channels"
    elif bad == "ndim":
        frames = np.ones((4, 3), np.float32)
        pat = r"\[n, H, W\]"
    elif bad == "count":
        t = np.array([0, 10, 20])
        pat = "3 timestamps for 4 frames"
    if bad == "no_fps":
        np.savez(tmp_path / "x.npz", frames=frames)
        err, pat = ConfigError, "fps"
    else:
        np.savez(tmp_path / "x.npz", frames=frames, t=t)
    with pytest.raises(err, match=pat):
        read_all(params, tmp_path)


def test_folder_with_mismatched_image_sizes(tmp_path):
    import imageio.v3 as iio

    iio.imwrite(tmp_path / "a.png", np.zeros((4, 6), np.uint8))
    iio.imwrite(tmp_path / "b.png", np.zeros((5, 6), np.uint8))
    with pytest.raises(DataError, match=r"b.png: frame shape \(5, 6\) differs"):
        read_all({"path": str(tmp_path), "fps": 30.0}, tmp_path)


def test_video_without_backend_says_what_to_install(tmp_path):
    pytest.importorskip("imageio")
    try:
        import av  # noqa: F401
        pytest.skip("a video backend is installed")
    except ImportError:
        pass
    (tmp_path / "v.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42" + b"\x00" * 64)
    with pytest.raises(DataError, match=r"imageio\[pyav\]"):
        read_all({"path": str(tmp_path / "v.mp4"), "fps": 30.0}, tmp_path)


def test_missing_path(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        read_all({"path": str(tmp_path / "nope.npz")}, tmp_path)
