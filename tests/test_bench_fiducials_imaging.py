"""`lab bench fiducials --only imaging`: its metrics read a known field back, and a small instance
of the study renders through the sim world's camera and orders its conditions as physics says."""

from __future__ import annotations

import numpy as np

from lab.studies import bench_fiducials_imaging as imaging

K = np.array([[914.0, 0.0, 639.5], [0.0, 914.0, 359.5], [0.0, 0.0, 1.0]])


def _square(cx: float, cy: float, half: float = 20.0) -> np.ndarray:
    return np.array([[cx - half, cy - half], [cx + half, cy - half], [cx + half, cy + half], [cx - half, cy + half]])


def test_a_focal_length_change_is_read_back_as_the_field_it_makes():
    df = 0.05                                  # px: every corner moved as a focal length df longer would
    sightings = []
    # tags on a grid symmetric about the principal point
    for u in np.linspace(-500, 500, 11):
        for v in np.linspace(-260, 260, 9):
            truth = _square(K[0, 2] + u, K[1, 2] + v)
            moved = K[:2, 2] + (truth - K[:2, 2]) * (1 + df / K[0, 0])
            sightings.append({"distance_m": 2.0 + u / 1000, "truth": truth, "corners": moved})
    m = imaging.metrics(sightings, K)
    assert abs(m["focal_px"] - df) < 1e-9
    assert m["outward_outer_px"][0] > m["outward_inner_px"][0] > 0
    # a shift that is not radial reads as no field
    shifted = [dict(s, corners=s["truth"] + [0.05, 0.0]) for s in sightings]
    assert abs(imaging.metrics(shifted, K)["focal_px"]) < 1e-9


def test_a_small_study_renders_every_condition_and_the_ideal_camera_is_the_cleanest():
    res = imaging.imaging_study(3, 0)
    rows = {r["condition"]: r for r in res["rows"]}
    assert set(rows) == set(imaging.CONDITIONS)
    assert all(r["sightings"] >= 15 for r in rows.values())        # of 18 tags each
    ideal, noise_free, default = (rows[k]["rms_px"] for k in ("noise-free, no light or bow", "noise-free", "default"))
    assert ideal < 0.02 < noise_free < default
    assert "| default |" in "\n".join(imaging.markdown(res))
