"""EXR / PNG / checkpoint files: bit-exact round trips, clear errors, atomic writes."""

import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from jprt import io

finite_or_inf = st.floats(width=32, allow_nan=False)


@settings(max_examples=20, deadline=None)
@given(image=arrays(np.float32, st.tuples(st.integers(1, 9), st.integers(1, 9), st.sampled_from([1, 3, 4])),
                    elements=finite_or_inf))
def test_float32_exr_round_trip_is_bit_exact(tmp_path_factory, image):
    path = str(tmp_path_factory.mktemp("exr") / "image.exr")
    io.write_exr(path, image)
    names = {1: "Y", 3: "RGB", 4: "RGBA"}[image.shape[2]]
    back = io.read_exr(path, channels=names)
    assert back.dtype == np.float32
    np.testing.assert_array_equal(back.view(np.uint32), image.view(np.uint32))


def test_float16_and_named_channels(tmp_path):
    rng = np.random.default_rng(0)
    image = rng.normal(size=(5, 7, 5)).astype(np.float16).astype(np.float32)
    names = ["u", "v", "roughness", "object_id", "valid"]
    path = str(tmp_path / "multi.exr")
    io.write_exr(path, image, channels=names, half=True)
    assert io.exr_channels(path) == sorted(names)
    np.testing.assert_array_equal(io.read_exr(path, channels=names), image)
    everything = io.read_exr(path, channels=None)
    np.testing.assert_array_equal(everything["roughness"], image[..., 2])


def test_wrong_channels_and_missing_files(tmp_path):
    path = str(tmp_path / "y.exr")
    io.write_exr(path, np.ones((3, 3), np.float32))
    with pytest.raises(ValueError, match=r"has channels \['Y'\], missing requested \['R', 'G', 'B'\]"):
        io.read_exr(path, channels="RGB")
    with pytest.raises(FileNotFoundError, match="EXR file not found"):
        io.read_exr(str(tmp_path / "nope.exr"))
    with pytest.raises(ValueError, match="channel names"):
        io.write_exr(str(tmp_path / "bad.exr"), np.ones((2, 2, 5), np.float32))
    open(str(tmp_path / "junk.exr"), "wb").write(b"not an exr file")
    with pytest.raises(ValueError, match="cannot read EXR"):
        io.read_exr(str(tmp_path / "junk.exr"))


def test_failed_write_leaves_nothing(tmp_path, monkeypatch):
    import OpenEXR

    path = str(tmp_path / "out.exr")
    io.write_exr(path, np.zeros((2, 2, 3), np.float32))
    before = open(path, "rb").read()

    def boom(self, filename):
        open(filename, "wb").write(b"partial")
        raise KeyboardInterrupt

    monkeypatch.setattr(OpenEXR.File, "write", boom)
    with pytest.raises(KeyboardInterrupt):
        io.write_exr(path, np.ones((2, 2, 3), np.float32))
    assert open(path, "rb").read() == before  # old file intact
    assert sorted(os.listdir(tmp_path)) == ["out.exr"]  # no temporary left behind


def test_png_preview(tmp_path):
    from PIL import Image

    ramp = np.linspace(0, 4, 30, dtype=np.float32).reshape(5, 6, 1).repeat(3, axis=2)
    path = str(tmp_path / "ramp.png")
    io.write_png(path, ramp)
    pixels = np.asarray(Image.open(path))
    assert pixels.shape == (5, 6, 3) and pixels.dtype == np.uint8
    assert (np.diff(pixels[..., 0].reshape(-1).astype(int)) >= 0).all()  # monotone tonemap
    assert pixels.max() == 255 and pixels.min() == 0
    bad = str(tmp_path / "nan.png")
    io.write_png(bad, np.array([[[np.nan, -1.0, 0.5]]], np.float32), mode="reinhard")
    assert tuple(np.asarray(Image.open(bad))[0, 0, :2]) == (0, 0)  # NaN and negative values preview as black


def test_checkpoint_round_trip_and_mismatch(tmp_path):
    import jax.numpy as jnp

    tree = {"layers": [{"w": jnp.arange(6.0).reshape(2, 3), "b": jnp.zeros(3)}], "step": np.int64(3),
            "scale": np.float64(0.1)}
    path = str(tmp_path / "ckpt.npz")
    io.save_checkpoint(path, tree, step=17, meta={"loss": 0.5})
    loaded, step, meta = io.load_checkpoint(path, like=tree)
    assert step == 17 and meta == {"loss": 0.5}
    np.testing.assert_array_equal(loaded["layers"][0]["w"], tree["layers"][0]["w"])
    assert loaded["scale"].dtype == np.float64
    with pytest.raises(ValueError, match="model has"):
        io.load_checkpoint(path, like={"layers": [{"w": jnp.zeros((3, 3)), "b": jnp.zeros(3)}], "step": np.int64(0),
                                       "scale": np.float64(0)})
    with pytest.raises(FileNotFoundError):
        io.load_checkpoint(str(tmp_path / "missing.npz"), like=tree)


def _rgbe_file(path, rgbe: np.ndarray, *, rle: bool) -> None:
    """A Radiance file of (H, W, 4) RGBE bytes: run-length encoded per channel (a run for each
    repeated value, literal spans otherwise) or flat."""
    h, w = rgbe.shape[:2]
    out = bytearray(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n" + f"-Y {h} +X {w}\n".encode())
    for y in range(h):
        if not rle:
            out += rgbe[y].tobytes()
            continue
        out += bytes([2, 2, w >> 8, w & 0xFF])
        for c in range(4):
            row, x = rgbe[y, :, c], 0
            while x < w:
                n = 1
                while x + n < w and n < 127 and row[x + n] == row[x]:
                    n += 1
                if n >= 3:
                    out += bytes([128 + n, row[x]])
                else:
                    n = min(w - x, 2)
                    out += bytes([n]) + row[x:x + n].tobytes()
                x += n
    with open(path, "wb") as f:
        f.write(bytes(out))


@pytest.mark.parametrize("rle", [True, False])
def test_read_hdr_decodes_rgbe(tmp_path, rle):
    rng = np.random.default_rng(0)
    rgbe = rng.integers(0, 256, size=(5, 16, 4), dtype=np.uint8)
    rgbe[1, 3:12] = [10, 20, 30, 130]  # runs
    rgbe[2, 5, 3] = 0  # exponent 0: black whatever the mantissas
    path = str(tmp_path / "map.hdr")
    _rgbe_file(path, rgbe, rle=rle)
    got = io.read_hdr(path)
    want = rgbe[..., :3].astype(np.float64) * np.exp2(rgbe[..., 3:].astype(np.float64) - 136)
    want[rgbe[..., 3] == 0] = 0
    assert got.dtype == np.float32 and got.shape == (5, 16, 3)
    np.testing.assert_array_equal(got, want.astype(np.float32))


def test_read_hdr_refuses_what_it_cannot_read(tmp_path):
    with pytest.raises(FileNotFoundError):
        io.read_hdr(str(tmp_path / "missing.hdr"))
    bad = tmp_path / "bad.hdr"
    bad.write_bytes(b"not an image")
    with pytest.raises(ValueError, match="not a Radiance HDR file"):
        io.read_hdr(str(bad))
    bad.write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n+Y 2 +X 2\n" + bytes(16))
    with pytest.raises(ValueError, match="resolution line"):
        io.read_hdr(str(bad))
    path = str(tmp_path / "cut.hdr")
    _rgbe_file(path, np.full((4, 16, 4), 7, np.uint8), rle=True)
    with open(path, "rb") as f:
        data = f.read()
    with open(path, "wb") as f:
        f.write(data[:-5])
    with pytest.raises(ValueError, match="cut.hdr"):
        io.read_hdr(path)


@pytest.mark.mitsuba
def test_read_hdr_equals_mitsuba(mi, tmp_path):
    """A map Mitsuba writes as .hdr reads back through jprt.io as through Mitsuba's Bitmap, bit for bit."""
    rng = np.random.default_rng(1)
    image = (rng.lognormal(-1.0, 2.0, size=(12, 40, 3)) * (rng.random((12, 40, 1)) > 0.1)).astype(np.float32)
    image[3, 5:30] = [0.5, 2.0, 8.0]  # a run
    path = str(tmp_path / "map.hdr")
    mi.Bitmap(image).write(path)
    bitmap = mi.Bitmap(path).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=False)
    np.testing.assert_array_equal(io.read_hdr(path), np.array(bitmap))
