"""calib.formats.dataset.DatasetWriter: one writer of ``dataset.json`` at a time. An acquisition writes its frames from
a worker
thread while its own thread records the run's state; both rewrite the document through the same temporary file."""

from __future__ import annotations

import threading

from calib.formats.dataset import BoardSpec, CameraSpec, Dataset, DatasetWriter, LegsSpec
from calib.model.parameters import NOMINAL


def test_frames_and_state_written_from_two_threads(tmp_path):
    w = DatasetWriter(
        tmp_path / "ds",
        camera=CameraSpec(width=8, height=8),
        board=BoardSpec(),
        legs=LegsSpec(rod_radius_m=0.008),
        nominal=NOMINAL.as_dict(),
    )
    n = 150
    errors: list[BaseException] = []

    def run(fn) -> None:
        try:
            for k in range(n):
                fn(k)
        except BaseException as exc:  # reported below: a lost temporary file, a document changed while dumped
            errors.append(exc)

    threads = [
        threading.Thread(target=run, args=(lambda k: w.add_frame("poses", [0.3, 0.3, 0.3, 0.3], None),)),
        threading.Thread(target=run, args=(lambda k: w.set_extra("acquisition", {"state": "running", "frames": k}),)),
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    ds = Dataset.open(tmp_path / "ds")
    assert len(ds.frames) == n
    assert ds.document.model_extra["acquisition"] == {"state": "running", "frames": n - 1}
