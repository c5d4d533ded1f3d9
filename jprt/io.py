"""Files: EXR images (OpenEXR), Radiance HDR images (read only), tonemapped PNG previews, pytree
checkpoints. Every write is atomic.

Atomic means: data goes to a temporary file in the destination folder, is flushed and fsync-ed,
and is renamed over the destination (``os.replace``), so a reader sees the old file or the new
one, never half of one, and an interrupted write leaves at most a ``*.tmp`` file behind.
``atomic_path`` and the checkpoints live in ``jprt.checkpoint`` (a leaf module the solvers use)
and are re-exported here.
"""

from __future__ import annotations

import io as _io
import json
import os
import re
from typing import Any, Sequence

import numpy as np

from jprt.checkpoint import CorruptCheckpoint, atomic_path, load_checkpoint, load_tree, save_checkpoint

__all__ = [
    "atomic_path",
    "atomic_write_bytes",
    "write_json",
    "write_exr",
    "read_exr",
    "read_hdr",
    "exr_channels",
    "write_png",
    "preview_pixels",
    "save_checkpoint",
    "load_checkpoint",
    "load_tree",
    "CorruptCheckpoint",
]


def atomic_write_bytes(path: str, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)


def write_json(path: str, obj: Any) -> None:
    """Write ``obj`` as indented JSON, atomically (NumPy scalars and arrays are converted)."""

    def default(o):
        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, np.generic):
            return o.item()
        raise TypeError(f"not JSON-serialisable: {type(o).__name__}")

    atomic_write_bytes(path, (json.dumps(obj, indent=2, sort_keys=True, default=default) + "\n").encode())


# --------------------------------------------------------------------------------------------
# EXR

_DEFAULT_NAMES = {1: ("Y",), 2: ("U", "V"), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}


def write_exr(path: str, image, channels: Sequence[str] | None = None, *, half: bool = False) -> None:
    """Write an (H, W) or (H, W, C) image to an EXR file, atomically.

    Args:
      image: float array. (H, W) is written as one channel "Y".
      channels: channel names, one per C; default Y / U,V / R,G,B / R,G,B,A by C.
      half: store float16 instead of float32 (float32 round-trips bit-exactly).
    """
    import OpenEXR

    image = np.asarray(image)
    if image.ndim == 2:
        image = image[..., None]
    if image.ndim != 3 or image.shape[0] == 0 or image.shape[1] == 0:
        raise ValueError(f"EXR image must be (H, W) or (H, W, C), got shape {image.shape}")
    c = image.shape[2]
    names = tuple(channels) if channels is not None else _DEFAULT_NAMES.get(c)
    if names is None or len(names) != c or len(set(names)) != c:
        raise ValueError(f"need {c} distinct channel names for an image with {c} channels, got {channels!r}")
    dtype = np.float16 if half else np.float32
    data = {name: np.ascontiguousarray(image[..., k].astype(dtype)) for k, name in enumerate(names)}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path, suffix=".exr") as tmp:
        OpenEXR.File(header, data).write(tmp)


def exr_channels(path: str) -> list[str]:
    """Channel names stored in an EXR file."""
    import OpenEXR

    if not os.path.isfile(path):
        raise FileNotFoundError(f"EXR file not found: {path}")
    with OpenEXR.File(path, separate_channels=True, header_only=True) as f:
        return sorted(ch.name for ch in f.header()["channels"])


def read_exr(path: str, channels: str | Sequence[str] | None = "RGB", dtype=np.float32):
    """Read channels of an EXR file.

    Args:
      channels: "RGB", "RGBA", "Y" (strings of one-letter names) or a list of names -> an
        (H, W, C) array in that order; None -> a dict of all channels as (H, W) arrays.
      dtype: output dtype (float16 files are widened exactly to float32).

    Raises:
      FileNotFoundError: no such file.
      ValueError: a requested channel is missing (one line naming those present).
    """
    import OpenEXR

    if not os.path.isfile(path):
        raise FileNotFoundError(f"EXR file not found: {path}")
    try:
        f = OpenEXR.File(path, separate_channels=True)
    except Exception as e:  # OpenEXR raises plain exceptions for corrupt files
        raise ValueError(f"cannot read EXR file {path}: {e}") from None
    with f:
        data = {name: ch.pixels for name, ch in f.channels().items()}
    if channels is None:
        return {k: np.asarray(v, dtype) for k, v in data.items()}
    names = list(channels)
    missing = [n for n in names if n not in data]
    if missing:
        raise ValueError(f"EXR file {path} has channels {sorted(data)}, missing requested {missing}")
    return np.stack([np.asarray(data[n], dtype) for n in names], axis=-1)


def read_hdr(path: str) -> np.ndarray:
    """Read a Radiance RGBE image (.hdr) as an (H, W, 3) float32 linear RGB array.

    A pixel (r, g, b, e) is (r, g, b) * 2^(e - 136) (0 where e = 0), the decoding of Walter's
    rgbe.c that Mitsuba's Bitmap uses, so the arrays equal Mitsuba's bit for bit. Scanlines are
    run-length encoded (the usual form) or flat; the resolution line must be ``-Y H +X W`` (rows
    from the top, the usual orientation).

    Raises:
      FileNotFoundError: no such file.
      ValueError: not an RGBE file, another orientation, or a damaged scanline (one line).
    """
    if not os.path.isfile(path):
        raise FileNotFoundError(f"HDR file not found: {path}")
    with open(path, "rb") as f:
        data = f.read()
    if not data.startswith((b"#?RADIANCE", b"#?RGBE")):
        raise ValueError(f"{path} is not a Radiance HDR file (no #?RADIANCE header)")
    end = data.find(b"\n\n")
    if end < 0:
        raise ValueError(f"{path}: the HDR header does not end")
    fmt = re.search(r"^FORMAT=(\S+)", data[:end].decode("latin-1"), re.M)
    if fmt and fmt.group(1) != "32-bit_rle_rgbe":
        raise ValueError(f"{path}: HDR format {fmt.group(1)}, only 32-bit_rle_rgbe is read")
    line_end = data.find(b"\n", end + 2)
    size = data[end + 2:line_end].decode("latin-1").split()
    if len(size) != 4 or size[0] != "-Y" or size[2] != "+X":
        raise ValueError(f"{path}: HDR resolution line {' '.join(size)!r}; only '-Y H +X W' is read")
    height, width = int(size[1]), int(size[3])
    buf = np.frombuffer(data, np.uint8, offset=line_end + 1)
    rgbe = np.empty((height, width, 4), np.uint8)
    pos = 0
    try:
        for y in range(height):
            if width < 8 or width > 0x7FFF or not (buf[pos] == 2 and buf[pos + 1] == 2 and buf[pos + 2] < 0x80):
                # not run-length encoded: the rest of the file is flat pixels
                rgbe[y:] = buf[pos:pos + (height - y) * width * 4].reshape(height - y, width, 4)
                break
            if (int(buf[pos + 2]) << 8 | int(buf[pos + 3])) != width:
                raise ValueError(f"{path}: scanline {y} is not {width} pixels long")
            pos += 4
            for c in range(4):  # each channel of the scanline: runs (count > 128) and literal spans
                x = 0
                while x < width:
                    count = int(buf[pos])
                    run = count > 128
                    count -= 128 if run else 0
                    if count == 0 or x + count > width:
                        raise ValueError(f"{path}: a bad run length in scanline {y}")
                    rgbe[y, x:x + count, c] = buf[pos + 1] if run else buf[pos + 1:pos + 1 + count]
                    pos += 2 if run else 1 + count
                    x += count
    except (IndexError, ValueError) as e:  # a truncated file ends inside a scanline
        raise ValueError(str(e) if str(e).startswith(path) else f"{path}: the HDR pixels end early") from None
    exponent = rgbe[..., 3:4].astype(np.int32)
    rgb = np.ldexp(rgbe[..., :3].astype(np.float32), exponent - 136).astype(np.float32)
    return np.where(exponent > 0, rgb, np.float32(0.0))


# --------------------------------------------------------------------------------------------
# PNG previews


def preview_pixels(image, *, exposure: float = 0.0, mode: str = "srgb", tonemapped: bool = False) -> np.ndarray:
    """The 8-bit display pixels of a linear HDR image (``jprt.metrics.tonemap``; NaN / inf shown
    black), or of [0, 1] values if ``tonemapped``: PNG previews and ``jprt view``'s frames."""
    image = np.asarray(image)
    if tonemapped:
        display = np.clip(image, 0.0, 1.0)
    else:
        from jprt.metrics import tonemap

        finite = np.nan_to_num(np.asarray(image, np.float32), nan=0.0, posinf=0.0, neginf=0.0)  # NaN / inf -> black
        display = np.asarray(tonemap(finite, exposure, mode))
    return np.round(display * 255.0).astype(np.uint8)


def write_png(path: str, image, *, exposure: float = 0.0, mode: str = "srgb", tonemapped: bool = False) -> None:
    """Write an 8-bit PNG preview of a linear HDR image (or of [0, 1] values if ``tonemapped``)."""
    from PIL import Image

    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    pixels = preview_pixels(image, exposure=exposure, mode=mode, tonemapped=tonemapped)
    buf = _io.BytesIO()
    Image.fromarray(pixels).save(buf, format="PNG")
    atomic_write_bytes(path, buf.getvalue())
