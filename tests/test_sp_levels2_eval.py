"""Evaluation of SP levels 2-3 and of appearance in classification on simulated drives
(``make eval``): the classes of the KD's objects with and without the appearance attributes
(LADAR reflectance, camera intensity), scored by the protocol of docs/evaluation.md; and how
much of the true walls the free-standing surfaces cover on sweeps where no object is
confirmed yet."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_sp_levels_eval import points_in_boxes, truth_pose_scores

import kd_store
from bench.results import record
from logs.types import GroundTruthPose, LadarScan, ObjectBoxes, TransformFrame
from sp.pipeline import SPConfig
from wm.entities import KDSensoryProcessor

CMD = "make eval"


@pytest.fixture(scope="module")
def village_log(tmp_path_factory) -> Path:
    """20 s of the village scenario on its own seed (a development seed): houses, walls,
    parked and moving vehicles, pedestrians, trees, bushes and posts."""
    from fixtures.simulate import simulate_to_log

    d = tmp_path_factory.mktemp("village-log")
    return simulate_to_log("village", d / "village.mcap", seconds=20.0, progress=False)


@pytest.mark.eval
def test_eval_classification_with_and_without_appearance(village_log: Path) -> None:
    """The node over a village drive (true poses) with the appearance SP observes by
    default (the camera's grey and excess green), with the LADAR's reflectance added
    (the simulator's albedo times shading, 0..1), and without appearance, each KD scored by
    the protocol (wm.evaluation). The fitted class library (kd_store/classes_fitted.yaml,
    wm.fit_classes) uses the excess green, a ratio of colour channels, but no
    brightness, since that depends on a sensor's calibration: adding the reflectance must
    leave every class as it was."""
    runs = {
        "no_appearance": SPConfig(appearance_classes=False),
        "appearance": SPConfig(),
        "reflectance": SPConfig(intensity_per_reflectance=1.0),
    }
    figs = {
        name: truth_pose_scores(village_log, village_log.with_name(f"{name}.kd"), sp)
        for name, sp in runs.items()
    }
    for name, fig in figs.items():
        record(
            f"sp_levels_classification_accuracy_{name}",
            fig["classification_accuracy"],
            "ratio",
            target=0.85,
            command=CMD,
        )
    print({name: (fig["classification_accuracy"], fig["mota"]) for name, fig in figs.items()})
    with_, reflectance = figs["appearance"], figs["reflectance"]
    assert with_["tp_pairs"] >= 300  # enough matched pairs to score
    assert reflectance["classification_accuracy"] == with_["classification_accuracy"]
    assert reflectance["mota"] == with_["mota"]
    # a guard below what SP reaches here with true poses (0.85 on this log; the target of
    # docs/evaluation.md, 0.85, is for the median over the evaluation seeds)
    assert with_["classification_accuracy"] >= 0.8


@pytest.mark.eval
def test_eval_free_surfaces_cover_the_true_walls() -> None:
    """Sweeps before the first object is confirmed (the walls still free): share of the
    returns on true walls and buildings that lie in a free surface (recall), and share of
    the free-surface returns that lie on one (precision)."""
    from fixtures.simulate import simulate

    kd = kd_store.open(":memory:")
    sp = KDSensoryProcessor(kd)
    T_body_ladar = T_world_body = boxes = None
    hit = on = surf = 0
    for f in simulate("default", seconds=1.0):
        if isinstance(f, TransformFrame) and f.child_frame_id == "ladar":
            T_body_ladar = f.T_parent_child
        elif isinstance(f, GroundTruthPose):
            T_world_body = f.T_parent_child
        elif isinstance(f, ObjectBoxes):
            boxes = f
        elif isinstance(f, LadarScan) and T_body_ladar is not None and boxes is not None:
            r = sp.process(f, T_world_body @ T_body_ladar)
            if any(kd.get(i).status == kd_store.Status.CONFIRMED for i in r.objects):
                break  # confirmed objects own their pixels: walls are no longer free
            s = np.isin(r.entity_images[3].reshape(-1)[r.point_pixel], r.surfaces)
            k = points_in_boxes(r.points_world, boxes, 0.5)
            wallish = np.array([c in ("building", "wall") for c in boxes.classes])
            w = (k >= 0) & wallish[np.maximum(k, 0)]
            hit += int((s & w).sum())
            on += int(w.sum())
            surf += int(s.sum())
    recall, precision = hit / max(on, 1), hit / max(surf, 1)
    record("sp_levels_free_surface_wall_recall", recall, "ratio", command=CMD)
    record("sp_levels_free_surface_wall_precision", precision, "ratio", command=CMD)
    assert precision >= 0.9 and recall >= 0.5
