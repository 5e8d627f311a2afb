import pytest

from models.erasenet.compute_report import STEPS, FrameCompute


def _report() -> FrameCompute:
    return FrameCompute(detect_macs=100, segment_macs=40, segment_executed_macs=55, detector_params=7,
                        segmenter_params=3, seconds={name: 0.001 * (i + 1) for i, name in enumerate(STEPS)},
                        roi_voxels=12, visited_points=30, detections=2)


def test_the_json_form_keeps_the_response_schema_and_its_totals():
    d = _report().to_dict()
    assert d["macs"] == {"detect": 100, "grow": 0, "segment": 40, "total": 140}
    assert d["executed_macs"] == {"detect": 100, "segment": 55, "total": 155}
    assert d["params"] == {"detector": 7, "segmenter": 3, "total": 10}
    assert list(d["seconds"]) == [*STEPS, "total"] and d["seconds"]["total"] == pytest.approx(0.015)
    assert (d["roi_voxels"], d["visited_points"], d["detections"]) == (12, 30, 2)


def test_added_seconds_make_a_new_report_whose_total_follows():
    report = _report()
    adc = report.plus_seconds("transform", 0.5)
    assert report.seconds["transform"] == pytest.approx(0.001)  # the original is untouched
    assert adc.seconds["transform"] == pytest.approx(0.501) and adc.seconds_total == pytest.approx(0.515)
    served = adc.plus_seconds("decode", 0.25, first=True)
    assert list(served.seconds) == ["decode", *STEPS]
    assert served.compute_us == 765_000
    rounded = served.seconds_by_stage(decimals=3)
    assert rounded["decode"] == 0.25 and rounded["total"] == 0.765
