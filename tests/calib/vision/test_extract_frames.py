"""extract_dataset(on_frame=...): one report per frame and stage, agreeing with the observations it returns."""

from __future__ import annotations

import pytest

from calib.vision.extract import ROD_PHASES, ExtractOptions, extract_dataset
from tests.calib.vision.test_extract import small_dataset  # noqa: F401  (the rendered, partly damaged dataset)


@pytest.mark.parametrize("workers", [1, 2])
def test_on_frame_reports_agree_with_the_observations(small_dataset, workers):  # noqa: F811
    root, _, _ = small_dataset
    infos: list[dict] = []
    # one pass (the damaged frames lose more than 5% of the rods looked for: no second look, which reports again)
    res = extract_dataset(root, workers=workers, on_frame=infos.append, options=ExtractOptions(recover_lost_share=None))
    frames = res.observations["frames"]
    by_stage = {st: {i["frame"]: i for i in infos if i["stage"] == st} for st in ("board", "rods")}
    # a frame measured again on the rods' refitted prediction is reported again (its last report counts)
    again = res.summary["repredicted"]["frames_measured_again"]
    assert len(infos) == 2 * len(frames) + again
    for st in ("board", "rods"):
        assert sorted(by_stage[st]) == [f["dataset_frame"] for f in frames], st
    # every board report comes before any rods report (the stages run in turn)
    assert [i["stage"] for i in infos] == ["board"] * len(frames) + ["rods"] * (len(frames) + again)
    for f in frames:
        b, r = by_stage["board"][f["dataset_frame"]], by_stage["rods"][f["dataset_frame"]]
        assert b["phase"] == r["phase"] == f["phase"]
        assert b["board"] is r["board"] is (f["board"] is not None)
        assert b["rods"] is None
        if f["board"] is not None:
            assert r["corners"] >= 6 and 0 < r["rms_px"] < 2
            assert r["detections"]["board"]["t"] == f["board"]["t"]
        n_rods = sum(x is not None for leg in f["legs"].values() for x in leg)
        assert r["rods"] == n_rods and r["rods_total"] == (8 if f["phase"] in ROD_PHASES else 0)
        assert r["detections"]["legs"] == f["legs"]
        assert set(r["missing"]) == set(f["missing"]), f["dataset_frame"]
    assert "image" in by_stage["rods"][8]["missing"] and by_stage["rods"][8]["rods"] == 0
    assert "board" in by_stage["board"][10]["missing"] and by_stage["rods"][10]["rods"] >= 6
