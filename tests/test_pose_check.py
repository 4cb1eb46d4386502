"""Camera poses of one capture state from its images alone, against the shipped poses."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from dsg_gym.cameras import look_at  # noqa: E402
from train_world.capture.pose_check import PoseEstimate, compare_poses  # noqa: E402

LLFF = Path(__file__).resolve().parents[2] / "shared" / "external" / "ethiopian_head_llff"


def _orbit(n=12):
    eyes = [(np.cos(a), np.sin(a), 0.5) for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]
    return [np.linalg.inv(look_at(np.array(e), np.zeros(3), np.array([0, 0, 1.0]))) for e in eyes]


def test_compare_poses_undoes_a_similarity():
    c2w = _orbit()
    s, ang = 0.4, np.radians(30)
    sim = np.eye(4)
    sim[:3, :3] = s * np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
    sim[:3, 3] = [0.3, -0.2, 1.0]
    est = {}
    for i, m in enumerate(c2w):  # the estimate lives in another frame: centres and rotations mapped by sim
        e = np.eye(4)
        e[:3, :3] = sim[:3, :3] / s @ m[:3, :3]
        e[:3, 3] = sim[:3, :3] @ m[:3, 3] + sim[:3, 3]
        est[f"{i:02d}"] = np.linalg.inv(e)
    r = compare_poses(PoseEstimate(est, {f"{i:02d}": m for i, m in enumerate(c2w)}, (1.0,), 12, 0.0))
    assert r["registered"] == 12 and r["similarity_scale"] == pytest.approx(1 / s)
    assert r["camera_centre_error_max"] < 1e-9 and r["camera_rotation_error_max_deg"] < 1e-6
    with pytest.raises(ValueError, match="need 3"):
        compare_poses(PoseEstimate(dict(list(est.items())[:2]), {}, (1.0,), 2, 0.0))


@pytest.mark.slow
@pytest.mark.skipif(
    not (LLFF / "poses_bounds.npy").is_file(), reason="shared/external/ethiopian_head_llff absent"
)
def test_ethiopian_head_poses_from_images_agree_with_the_shipped_ones(tmp_path):
    pytest.importorskip("pycolmap", reason="needs the capture extra")
    from train_world.capture.importers import import_llff
    from train_world.capture.pose_check import estimate_state_poses

    cap = import_llff(LLFF, tmp_path / "cap", factor=8)
    (tmp_path / "work").mkdir()
    r = compare_poses(estimate_state_poses(cap, "state1", tmp_path / "work", features="object"))
    print(r)
    # a turntable: features on the turning head only; regression bounds about twice what this gives
    assert r["registered"] >= 0.5 * r["views"]
    assert r["camera_centre_error_median_percent_of_radius"] < 5.0
    assert r["camera_rotation_error_median_deg"] < 4.0
