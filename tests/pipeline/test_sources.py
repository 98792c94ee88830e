"""File sources: looping past the end, and playing in real time like a camera (live: true)."""

from __future__ import annotations

import re

import pytest

from pipeline.gst import Gst
from tests.conftest import run_cli

CLIP_FRAMES = 10  # one second at 10 frames/s


@pytest.fixture(scope="module")
def short_clip(tmp_path_factory):
    """A one-second H.264 MP4, so that a few seconds of a run loop it several times."""
    path = tmp_path_factory.mktemp("clips") / "second.mp4"
    pipeline = Gst.parse_launch(
        f"videotestsrc num-buffers={CLIP_FRAMES} pattern=ball ! video/x-raw,width=320,height=240,framerate=10/1 "
        f'! x264enc speed-preset=ultrafast ! mp4mux ! filesink location="{path}"')
    pipeline.set_state(Gst.State.PLAYING)
    message = pipeline.get_bus().timed_pop_filtered(30 * Gst.SECOND, Gst.MessageType.EOS | Gst.MessageType.ERROR)
    pipeline.set_state(Gst.State.NULL)
    assert message is not None and message.type == Gst.MessageType.EOS
    return path


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
    assert 0.7 * 10 * seconds <= frames <= 10 * seconds + 3, (frames, seconds)
