"""File sources: looping past the end, and playing in real time like a camera (live: true)."""

from __future__ import annotations

import re

import pytest

from tests.conftest import run_cli
from tests.pipeline.clips import MJPEG_MULTIPART, write_clip

CLIP_FRAMES = 10  # one second at 10 frames/s


@pytest.fixture(scope="module")
def short_clip(tmp_path_factory):
    """A one-second H.264 MP4, so that a few seconds of a run loop it several times."""
    return write_clip(tmp_path_factory.mktemp("clips") / "second.mp4", CLIP_FRAMES)


def run_source(tmp_path, clip, source: str, *limit: str) -> tuple[int, float]:
    config = tmp_path / "loop.yaml"
    config.write_text(f"sources:\n  - {{uri: {clip}, loop: true, {source}}}\n"
                      "stages:\n  - mux: {width: 320, height: 240}\n  - tiler: {width: 320, height: 240}\n"
                      "  - convert: {format: RGBA}\n  - osd: {}\nsink: {type: fake, sync: false}\n")
    result = run_cli("run", config, *limit, cwd=tmp_path, timeout=120)
    assert result.returncode == 0, result.stderr
    frames, seconds = re.search(r"(\d+) frames in ([\d.]+) s", result.stderr).groups()
    return int(frames), float(seconds)


def test_a_looping_file_plays_on_past_its_end(tmp_path, short_clip):
    frames, _ = run_source(tmp_path, short_clip, "rate: 10", "--num-frames", str(4 * CLIP_FRAMES + 5))
    assert frames == 4 * CLIP_FRAMES + 5


def test_a_live_file_comes_in_real_time_across_its_loops(tmp_path, short_clip):
    """Paced by the clock, not by the pipeline: 10 frames/s through four loops of the clip.
    Without pacing (or with the loop's time offset after the pacing) it runs at hundreds."""
    frames, seconds = run_source(tmp_path, short_clip, "rate: 10, live: true", "--duration", "4")
    # The pacing is the upper bound; the lower one only says it ran (a loaded fresh clone, load ~18,
    # got 30 frames in 4.4 s: a live source drops what comes late).
    assert 0.5 * 10 * seconds <= frames <= 10 * seconds + 3, (frames, seconds)


def test_a_file_that_cannot_loop_says_so(tmp_path):
    """Multipart JPEG has no length to loop by: the source used to end without a word."""
    clip = write_clip(tmp_path / "clip.mjpeg", CLIP_FRAMES, MJPEG_MULTIPART)
    config = tmp_path / "noloop.yaml"
    config.write_text(f"sources:\n  - {{uri: {clip}, loop: true}}\nstages:\n  - queue: {{}}\nsink: {{type: fake, sync: false}}\n")
    result = run_cli("run", config, "--num-frames", str(3 * CLIP_FRAMES), cwd=tmp_path, timeout=120)
    assert result.returncode == 0, result.stderr
    assert f"warning: source 0 (uri:{clip.as_uri()}): cannot loop: its length is unknown" in result.stderr, result.stderr
    assert f"{CLIP_FRAMES} frames in" in result.stderr


def test_a_live_source_that_ends_is_reported_while_the_others_go_on(tmp_path, short_clip):
    config = tmp_path / "ends.yaml"
    config.write_text(f"sources:\n  - {{uri: {short_clip}, live: true}}\n  - {{test: ball, live: true, rate: 10}}\n"
                      "stages:\n  - mux: {batch-size: 2, width: 320, height: 240, live-source: true}\n  - queue: {}\n")
    result = run_cli("run", config, "--duration", "3", cwd=tmp_path, timeout=120)
    assert result.returncode == 0, result.stderr
    said = f"source 0 (uri:{short_clip.as_uri()}) ended: end of stream after {CLIP_FRAMES} frames; the other sources go on"
    assert said in result.stderr, result.stderr
    frames, seconds = re.search(r"(\d+) frames in ([\d.]+) s", result.stderr).groups()
    assert float(seconds) >= 2.9  # the ball went on after the clip's end


def test_a_single_live_source_that_ends_is_reported_too(tmp_path, short_clip):
    config = tmp_path / "ends.yaml"
    config.write_text(f"sources:\n  - {{uri: {short_clip}, live: true}}\nstages:\n  - queue: {{}}\n")
    result = run_cli("run", config, "--duration", "10", cwd=tmp_path, timeout=120)
    assert result.returncode == 0, result.stderr
    assert f"source 0 (uri:{short_clip.as_uri()}) ended: end of stream after {CLIP_FRAMES} frames\n" in result.stderr
