"""Evaluation of SP levels 2-3 and of appearance in classification on the simulated default
drive (``make eval``): classification accuracy of the confirmed objects with and without
the appearance attributes (LADAR reflectance, camera intensity), the camera frames fed to the
pipeline as the node does; and how much of the true walls the free-standing surfaces cover
on sweeps where no object is confirmed yet."""

from __future__ import annotations

import numpy as np
import pytest
from test_sp_levels_eval import MotTally, points_in_boxes, score_cycle

import kd_store
from bench.results import record
from logs.types import CameraFrame, GroundTruthPose, LadarScan, ObjectBoxes, TransformFrame
from sp.pipeline import SPConfig
from wm.entities import KDSensoryProcessor

CMD = "make eval"


def run_with_camera(
    appearance: bool, reflectance: float | None = None, seconds: float = 20.0
) -> dict[str, float]:
    """The default scenario through SP with the camera frames; the tracking figures.
    ``reflectance``: the LADAR's intensity per unit reflectance (None: not used)."""
    from fixtures.simulate import simulate

    kd = kd_store.open(":memory:")
    cfg = SPConfig(appearance_classes=appearance, intensity_per_reflectance=reflectance)
    sp = KDSensoryProcessor(kd, cfg)
    tally = MotTally()
    T_body_ladar = T_body_camera = T_world_body = None
    boxes: ObjectBoxes | None = None
    camera: CameraFrame | None = None
    for f in simulate("default", seconds=seconds):
        if isinstance(f, TransformFrame) and f.child_frame_id == "ladar":
            T_body_ladar = f.T_parent_child
        elif isinstance(f, TransformFrame) and f.child_frame_id == "camera":
            T_body_camera = f.T_parent_child
        elif isinstance(f, GroundTruthPose):
            T_world_body = f.T_parent_child
        elif isinstance(f, ObjectBoxes):
            boxes = f
        elif isinstance(f, CameraFrame):
            camera = f
        elif isinstance(f, LadarScan) and T_body_ladar is not None and T_world_body is not None:
            T_cam = None if T_body_camera is None else T_world_body @ T_body_camera
            result = sp.process(f, T_world_body @ T_body_ladar, camera=camera, T_world_camera=T_cam)
            if boxes is not None and boxes.t_ns == f.t_ns:
                score_cycle(tally, kd, sp, result, boxes)
    return tally.figures()


@pytest.mark.eval
def test_eval_classification_with_and_without_appearance() -> None:
    without = run_with_camera(False)
    camera = run_with_camera(True)  # the default: camera grey only (LADAR units unknown)
    # and the LADAR's reflectance too: the simulator reports albedo times shading, 0..1
    with_ = run_with_camera(True, reflectance=1.0)
    runs = (("no_appearance", without), ("camera", camera), ("appearance", with_))
    for name, fig in runs:
        record(
            f"sp_levels_classification_accuracy_{name}",
            fig["classification_accuracy"],
            "ratio",
            target=0.9,
            command=CMD,
        )
    record("sp_levels_mota_camera", with_["mota"], "ratio", target=0.9, command=CMD)
    for _, fig in runs:
        assert fig["classification_accuracy"] >= 0.9
        assert fig["classification_accuracy"] >= without["classification_accuracy"] - 0.02


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
