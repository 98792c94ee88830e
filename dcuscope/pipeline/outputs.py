"""Where a run writes its frames, checked before anything runs.

A video file's container comes from its name (``.mp4``, ``.mkv``, ``.avi``); a folder gets
numbered PNG frames. Nothing is created here: a missing folder or one that cannot be written is
a bad argument, said in one line, not a surprise folder or an error from inside the pipeline.
"""

from __future__ import annotations

import os
from pathlib import Path

CONTAINERS = {".mp4": "mp4mux", ".m4v": "mp4mux", ".mov": "qtmux", ".mkv": "matroskamux", ".avi": "avimux"}
"""Video file suffix -> the GStreamer muxer that writes that container (H.264 inside)."""
FRAME_PATTERN = "frame_%05d.png"
FRAME_GLOB = "frame_*.png"


def check_video_file(path: Path) -> str | None:
    """Why ``path`` cannot take a new video file, or None."""
    if path.suffix.lower() not in CONTAINERS:
        return (f"unknown video container {path.suffix or '(no suffix)'!r} "
                f"(expected one of {', '.join(CONTAINERS)}, or a folder/ for PNG frames)")
    if path.is_dir():
        return "is a folder (write a video file into it, or end the path with / for PNG frames)"
    return _check_writable(path)


def check_frames_folder(path: Path) -> str | None:
    """Why ``path`` cannot take new PNG frames, or None. Frames of an earlier run are not
    overwritten one by one: a shorter run would leave old frames after the new ones."""
    if path.exists() and not path.is_dir():
        return "is a file, not a folder for PNG frames"
    if path.is_dir():
        if next(path.glob(FRAME_GLOB), None) is not None:
            return f"already holds {FRAME_GLOB} frames of an earlier run: remove them or pick another folder"
        return _check_writable(path / FRAME_PATTERN.replace("%05d", "00000"))
    if not path.parent.is_dir():
        return f"folder {path.parent} does not exist"
    try:
        path.mkdir()  # the only way to know, whoever runs it (root passes access())
        path.rmdir()
    except OSError as exc:
        return f"cannot create the folder: {exc.strerror}"
    return None


def _check_writable(path: Path) -> str | None:
    if not path.parent.is_dir():
        return f"folder {path.parent} does not exist"
    if path.exists():
        return None if path.is_file() and os.access(path, os.W_OK) else "cannot be written"
    try:
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644))
        path.unlink()
    except OSError as exc:
        return f"cannot be written: {exc.strerror}"
    return None
