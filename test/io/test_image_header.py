"""The size an encoded image declares (epi_vo.io.image_header) and what compressed_to_gray does with it: an
image that would decode into too many pixels, or into another size than camera_info's, is refused without
being decoded; an EXIF orientation is not applied (ROS's compressed transport does not apply it)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import pytest
from encoded_images import big_png, png_header, with_exif_orientation

from epi_vo.core.errors import ImageConversionError
from epi_vo.io import msgconv
from epi_vo.io.msgconv import compressed_to_gray

GRAY = (np.arange(48 * 64).reshape(48, 64) * 7 % 251).astype(np.uint8)


def _encoded(ext: str, img: np.ndarray = GRAY, *params: int) -> bytes:
    ok, buf = cv2.imencode(ext, img, list(params))
    assert ok
    return buf.tobytes()


def _msg(data: bytes, fmt: str = "png") -> SimpleNamespace:
    return SimpleNamespace(format=fmt, data=np.frombuffer(data, np.uint8))


@pytest.fixture
def imdecode_calls(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """Every call of cv2.imdecode, with what it returned."""
    calls: list[Any] = []
    real = cv2.imdecode

    def spy(buf: Any, flags: int) -> Any:
        out = real(buf, flags)
        calls.append(None if out is None else out.shape)
        return out

    monkeypatch.setattr(msgconv.cv2, "imdecode", spy)
    return calls


def test_declared_sizes() -> None:
    from epi_vo.io.image_header import DeclaredSize, declared_size

    def size(data: bytes) -> object:
        return declared_size(np.frombuffer(data, np.uint8))

    assert size(_encoded(".png")) == DeclaredSize(64, 48, "png")
    assert size(_encoded(".jpg")) == DeclaredSize(64, 48, "jpeg")
    assert size(_encoded(".jpg", GRAY, cv2.IMWRITE_JPEG_PROGRESSIVE, 1)) == DeclaredSize(64, 48, "jpeg")
    assert size(with_exif_orientation(_encoded(".jpg"), 6)) == DeclaredSize(64, 48, "jpeg")
    assert size(png_header(30000, 30000)) == DeclaredSize(30000, 30000, "png")
    assert "neither a JPEG nor a PNG" in size(_encoded(".bmp"))
    assert "no IHDR" in size(_encoded(".png")[:20])
    assert "no frame header" in size(_encoded(".jpg")[:30])


def test_an_image_declaring_too_many_pixels_is_not_decoded(imdecode_calls: list[Any]) -> None:
    """10000 x 10000 (100 Mpx, over the cap) in a few hundred kilobytes; 30000 x 30000 would take gigabytes."""
    data = big_png(10000, 10000)
    assert len(data) < 1_000_000
    with pytest.raises(ImageConversionError, match=r"its PNG header declares 10000x10000 pixels, more than the "
                                                   r"67108864 an image may have \(not decoded\)"):
        compressed_to_gray(_msg(data))
    with pytest.raises(ImageConversionError, match="declares 30000x30000 pixels"):
        compressed_to_gray(_msg(png_header(30000, 30000) + bytes(1000)))
    assert imdecode_calls == []


def test_an_image_of_another_size_than_camera_info_is_not_decoded(imdecode_calls: list[Any]) -> None:
    data = big_png(4000, 3000)
    with pytest.raises(ImageConversionError, match=r"image size 4000x3000 does not match camera_info size 640x480 "
                                                   r"\(declared by its PNG header, not decoded\)"):
        msgconv.decode_frame(_msg(data), True, (640, 480))
    assert imdecode_calls == []
    assert compressed_to_gray(_msg(_encoded(".png")), (64, 48)).shape == (48, 64)
    assert imdecode_calls == [(48, 64)]


def test_exif_orientation_is_not_applied() -> None:
    """A rotated camera's JPEG tagged "rotate 90": the pixels are the sensor's, as camera_info describes them."""
    plain = compressed_to_gray(_msg(_encoded(".jpg"), "jpeg"))
    for orientation in (3, 6, 8):
        tagged = compressed_to_gray(_msg(with_exif_orientation(_encoded(".jpg"), orientation), "jpeg"), (64, 48))
        assert tagged.shape == (48, 64)
        np.testing.assert_array_equal(tagged, plain)


def test_a_long_format_string_is_cut_in_the_error() -> None:
    with pytest.raises(ImageConversionError) as exc:
        compressed_to_gray(_msg(b"garbage", "x" * 1_000_000))
    assert len(str(exc.value)) < 300 and "(1000000 characters)" in str(exc.value)
