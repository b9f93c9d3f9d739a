"""Marker blobs in every image of every camera, decoded and detected on threads.

Decoding can cost more than detecting the blobs (a 1280x720 grey frame: a deflated PNG 13
CPU-ms, an MJPG frame 2.3, against ~1.5 for the detection), so a command that reads images must
use every core for both. OpenCV's decoders and the compiled blob pass release the GIL, so
threads do it: each photo or MJPG frame is one task (read + detect), each other video one task
per camera (FFmpeg decodes it in order). Results are taken in camera and frame order, so they do
not depend on the thread count. Only each camera's first image is kept (for the overlay).
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np

from mocaptk.errors import InputFileError
from mocaptk.threads import machine_workers

from .blob_detection import Blobs, detect_blobs
from .image_sequences import ImageSource, decode_jpeg, read_grey
from .scratch import Scratch

#: (frame name, (width, height) px, the image (first frame only, else None), its blobs)
_Result = tuple[str, tuple[int, int], np.ndarray | None, Blobs]
_buffers = threading.local()


def detect_sources(sources: list[ImageSource], *, min_area: int, max_area: int,
                   threads: int | None = None) -> tuple[list[list[Blobs]], list[np.ndarray | None]]:
    """Per camera the :class:`Blobs` of every frame (merged blobs split in two) and its first
    image (None without frames), on ``threads`` threads (default: one per usable CPU,
    :func:`mocaptk.threads.machine_workers`). Raises the
    InputFileError of the first bad image in camera and frame order."""
    options = {"min_area": min_area, "max_area": max_area, "split": True}
    threads = threads or machine_workers()
    pool = ThreadPoolExecutor(threads, thread_name_prefix="mocaptk-detect")
    rows: list[list[Blobs]] = [[] for _ in sources]
    firsts: list[np.ndarray | None] = [None] * len(sources)
    sizes: list[tuple[int, int] | None] = [None] * len(sources)
    try:
        for camera, done in _in_order(pool, _tasks(sources, options), depth=4 * threads):
            for name, shape, image, blobs in done:
                sizes[camera] = sources[camera].check_size(name, shape, sizes[camera])
                firsts[camera] = image if image is not None else firsts[camera]
                rows[camera].append(blobs)
        return rows, firsts
    finally:
        pool.shutdown(cancel_futures=True)  # after a bad image: no waiting for the rest


def _tasks(sources: list[ImageSource], options: dict) -> Iterator[tuple[int, Callable, tuple]]:
    """``(camera, function, arguments)``: one task per photo or MJPG frame, one per other video
    (decoded in order by FFmpeg); MJPG packets are read here, as the tasks are taken."""
    for camera, source in enumerate(sources):
        packets = source.jpeg_frames()
        if packets is not None:
            for index, (name, data) in enumerate(packets):
                yield camera, _jpeg, (source, name, data, options, index == 0)
        elif source.is_video:
            yield camera, _video, (source, options)
        else:
            for index, file in enumerate(source.files()):
                yield camera, _photo, (file, options, index == 0)


def _in_order(pool: ThreadPoolExecutor, tasks: Iterator[tuple[int, Callable, tuple]], *,
              depth: int) -> Iterator[tuple[int, list[_Result]]]:
    """Each task's ``(camera, results)`` in task order, at most ``depth`` tasks queued (a long
    video's packets are not all held at once)."""
    pending: deque[tuple[int, Future]] = deque()
    for camera, function, arguments in tasks:
        pending.append((camera, pool.submit(function, *arguments)))
        if len(pending) >= depth:
            camera, future = pending.popleft()
            yield camera, future.result()
    while pending:
        camera, future = pending.popleft()
        yield camera, future.result()


def _photo(file: Path, options: dict, keep: bool) -> list[_Result]:
    scratch = _scratch()
    image = read_grey(file, scratch=scratch)
    return [(file.name, (image.shape[1], image.shape[0]), image.copy() if keep else None,
             detect_blobs(image, scratch=scratch, **options))]


def _jpeg(source: ImageSource, name: str, data: np.ndarray, options: dict, keep: bool) -> list[_Result]:
    image = decode_jpeg(data)
    if image is None:
        raise InputFileError(source.path, f"{name}: cannot decode this MJPG frame")
    return [(name, (image.shape[1], image.shape[0]), image if keep else None,
             detect_blobs(image, scratch=_scratch(), **options))]


def _video(source: ImageSource, options: dict) -> list[_Result]:
    scratch = _scratch()
    return [(name, (image.shape[1], image.shape[0]), None if index else image,
             detect_blobs(image, scratch=scratch, **options))
            for index, (name, image) in enumerate(source.frames())]


def _scratch() -> Scratch:
    """The calling thread's buffers (a pool thread runs one task at a time)."""
    if not hasattr(_buffers, "scratch"):
        _buffers.scratch = Scratch()
    return _buffers.scratch

