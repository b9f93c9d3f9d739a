"""Reading uncompressed grey PNGs without libpng: the same pixels as OpenCV, OpenCV for any other
PNG, and a cut file is still an error."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mocaptk.acquisition.image_sequences import read_grey
from mocaptk.acquisition.scratch import Scratch
from mocaptk.acquisition.stored_png import read_stored, stored_size
from mocaptk.acquisition.synth_images import png_bytes
from mocaptk.errors import InputFileError


@pytest.fixture(scope="module")
def image():
    rng = np.random.default_rng(3)
    return rng.integers(0, 256, (301, 157), dtype=np.uint8)  # odd sizes: rows cross chunks and blocks


def test_synth_png_is_read_without_libpng_to_the_same_pixels(tmp_path, image):
    data = png_bytes(image)
    size = stored_size(data[:33])
    assert size == (157, 301)
    out, rows = np.empty((301, 157), np.uint8), np.empty((301, 158), np.uint8)
    assert read_stored(memoryview(data), out, rows)
    assert np.array_equal(out, image)
    file = tmp_path / "frame.png"
    file.write_bytes(data)
    scratch = Scratch()
    assert np.array_equal(read_grey(file, scratch=scratch), cv2.imread(str(file), cv2.IMREAD_GRAYSCALE))
    assert np.array_equal(read_grey(file, scratch=scratch), image)  # buffers reused


@pytest.mark.parametrize("options", [
    [cv2.IMWRITE_PNG_COMPRESSION, 0, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_PAETH],
    [cv2.IMWRITE_PNG_COMPRESSION, 3],
])
def test_filtered_or_deflated_png_is_left_to_opencv(tmp_path, image, options):
    data = cv2.imencode(".png", image, options)[1].tobytes()
    out, rows = np.empty((301, 157), np.uint8), np.empty((301, 158), np.uint8)
    assert not read_stored(memoryview(data), out, rows)
    file = tmp_path / "frame.png"
    file.write_bytes(data)
    assert np.array_equal(read_grey(file), image)


def test_colour_png_is_left_to_opencv(tmp_path, image):
    colour = np.dstack([image, image // 2, 255 - image])
    data = cv2.imencode(".png", colour, [cv2.IMWRITE_PNG_COMPRESSION, 0])[1].tobytes()
    assert stored_size(data[:33]) is None
    file = tmp_path / "frame.png"
    file.write_bytes(data)
    assert np.array_equal(read_grey(file), cv2.imread(str(file), cv2.IMREAD_GRAYSCALE))


def test_a_cut_stored_png_is_an_error(tmp_path, image):
    data = png_bytes(image)
    out, rows = np.empty((301, 157), np.uint8), np.empty((301, 158), np.uint8)
    for cut in (len(data) - 20, len(data) // 2, 40):
        assert not read_stored(memoryview(data[:cut]), out, rows)
    file = tmp_path / "frame.png"
    file.write_bytes(data[:len(data) // 2])
    with pytest.raises(InputFileError, match="cannot decode"):
        read_grey(file)


def test_a_png_header_claiming_a_huge_image_allocates_nothing_big(tmp_path, image):
    data = bytearray(png_bytes(image))
    data[16:24] = (60000).to_bytes(4, "big") * 2  # IHDR: 60000 x 60000 px, 3.6 GB of rows
    file = tmp_path / "frame.png"
    file.write_bytes(bytes(data))
    scratch = Scratch()
    with pytest.raises(InputFileError, match="cannot decode"):
        read_grey(file, scratch=scratch)
    assert not scratch._buffers  # left to OpenCV, which refuses it
