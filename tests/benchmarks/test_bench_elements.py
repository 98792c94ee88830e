"""benchmarks/bench_elements.py: a case that fails is n/a with its error, and the --quick run prints
every case and every ratio."""

from __future__ import annotations

from benchmarks.bench_elements import measure, rgb_caps, stamped
from benchmarks.figures import NA, ratio
from tests.benchmarks.smoke import assert_ran, run_benchmark

CASES = ["tiler", "compositor", "convert RGBA", "videoconvert RGBA", "videoconvert n-threads=0 RGBA", "convert I420",
         "videoconvert I420", "videoconvert n-threads=0 I420"]


def test_a_case_that_cannot_run_is_n_a_with_its_error_and_so_is_every_ratio_of_it():
    fps = measure("appsrc name=src ! nosuchelement ! fakesink name=sink sync=false", {})
    assert isinstance(fps, NA) and "cannot make the pipeline" in fps.reason and "nosuchelement" in fps.reason
    assert ratio(100.0, fps) is fps


def test_a_case_whose_pipeline_fails_is_n_a_with_the_error_from_the_bus():
    # caps the sink cannot take: the appsrc's first push fails to negotiate
    buffers = [stamped([], i) for i in range(3)]
    fps = measure("appsrc name=src ! video/x-raw,format=GRAY8 ! fakesink name=sink sync=false",
                  {"src": (rgb_caps(), buffers)})
    assert isinstance(fps, NA) and fps.reason.startswith("error from "), fps


def test_quick_mode_prints_every_case_and_every_ratio():
    done = run_benchmark("bench_elements.py", "--quick")
    assert_ran(done)
    lines = done.stdout.splitlines()
    medians = lines[lines.index("median frames/s (min..max over repetitions)") + 1:][:len(CASES)]
    assert [line.split("  ")[1].strip() for line in medians] == CASES
    ratios = lines[lines.index("ratios, ours / GStreamer's C element (> 1: ours is faster)") + 1:][:5]
    assert [line.split()[0] for line in ratios] == ["tiler"] + ["convert"] * 4
