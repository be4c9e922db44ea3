"""benchmarks/compare.py: which way each headline figure is better, and the means over repeats."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
_spec = importlib.util.spec_from_file_location("bench_compare", ROOT / "benchmarks" / "compare.py")
compare = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(compare)


@pytest.mark.parametrize("key, better", [
    ("wall_s", "lower"), ("exact.cpu_s", "lower"), ("h5_peak_rss_MB", "lower"), ("drift_error_ppm", "lower"),
    ("sync_s_per_session", "lower"), ("paper_single_tap_std_ms", "lower"),
    ("frames_per_s", "higher"), ("vectornav_frames_decoded_per_s_one_buffer", "higher"),
    ("sim_to_wall_ratio", "higher"), ("speedup_2_workers", "higher"), ("h5_exit", "?"),
])
def test_direction_from_the_key_name(key: str, better: str) -> None:
    assert compare.direction(key) == better


def test_means_over_repeats_and_the_first_error() -> None:
    runs = [({"a": 1.0, "b": {"c": 3}}, 10.0, ""), ({"a": 3.0, "b": {"c": 5}, "d": 1}, 20.0, "")]
    figs, wall, why = compare.mean_of(runs)
    assert figs == {"a": 2.0, "b.c": 4.0} and wall == 15.0 and why == ""
    assert compare.mean_of(runs + [({}, 0.0, "exit 1")]) == ({}, 0.0, "exit 1")
