"""benchmarks/bench_infer_cpu.py and bench_infer_providers.py --quick: their JSON lines; a provider
list this onnxruntime lacks is left out with its reason, and with none left the benchmark says so
in one line; a batch larger than the frames is n/a with the reason."""

from __future__ import annotations

import onnxruntime as ort

from tests.benchmarks.smoke import assert_cannot_run, assert_ran, json_lines, run_benchmark


def test_infer_cpu_quick_mode_gives_the_ssd_model_with_and_without_spinning():
    done = run_benchmark("bench_infer_cpu.py", "--quick")
    assert_ran(done)
    rows = json_lines(done.stdout)
    assert [r["model"] for r in rows] == ["ssdlite_mobilenetv2_person.onnx"]
    for r in rows:
        assert set(r["no_spin"]) == set(r["spin"]) == {"wall_ms", "cpu_ms"} and r["no_spin"]["wall_ms"] > 0
        assert {"cpu_ratio_spin_vs_no_spin", "wall_ratio_spin_vs_no_spin"} <= set(r)


def test_infer_providers_quick_mode_compares_what_this_onnxruntime_has_and_says_what_it_left_out():
    done = run_benchmark("bench_infer_providers.py", "--quick")
    assert_ran(done)
    header, *rows = json_lines(done.stdout)
    assert header["model"] == "ssd" and header["available"] == ort.get_available_providers()
    cuda = "CUDAExecutionProvider" in ort.get_available_providers()
    skipped = [r for r in rows if "skipped" in r]
    assert [r["providers"] for r in skipped] == ([] if cuda else ["CUDAExecutionProvider,CPUExecutionProvider"])
    assert all(r["skipped"] == "not in this onnxruntime: CUDAExecutionProvider" for r in skipped)
    measured = [(r["providers"], r["batch"]) for r in rows if "skipped" not in r]
    lists = ["CPUExecutionProvider"] + (["CUDAExecutionProvider,CPUExecutionProvider"] if cuda else [])
    assert measured == [(p, b) for b in (1, 2) for p in lists]
    for r in rows:
        if "skipped" not in r:
            assert r["ms_per_batch"] > 0 and r["agreement"]["frames"] == 4


def test_a_batch_larger_than_the_frames_is_n_a_with_the_reason():
    done = run_benchmark("bench_infer_providers.py", "--providers", "CPUExecutionProvider", "--model", "ssd",
                         "--frames", "1", "--batches", "2", "--repeat", "1")
    assert_ran(done)
    [row] = json_lines(done.stdout)[1:]
    why = "n/a (a batch of 2 is more than the 1 frames)"
    assert row["ms_per_batch"] == row["frames_per_s"] == row["speedup_vs_CPUExecutionProvider"] == why


def test_with_no_provider_list_it_can_run_it_says_so_in_one_line():
    done = run_benchmark("bench_infer_providers.py", "--quick", "--providers", "NoSuchExecutionProvider")
    assert_cannot_run(done, "bench_infer_providers.py", "no provider list can run here: NoSuchExecutionProvider "
                                                        "(not in this onnxruntime: NoSuchExecutionProvider)")
    assert json_lines(done.stdout)[1] == {"providers": "NoSuchExecutionProvider",
                                          "skipped": "not in this onnxruntime: NoSuchExecutionProvider"}
