"""Metric scale from an ArUco marker: dsg-synth lays one on the table, dsg-capture measures it."""

from __future__ import annotations

import json
import os

os.environ.setdefault("MUJOCO_GL", "egl")

from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402  (numpy and Pillow before pycolmap)
import pytest  # noqa: E402

cv2 = pytest.importorskip("cv2", reason="the marker needs OpenCV (the capture extra)")
pytest.importorskip("pycolmap", reason="dsg-capture needs pycolmap (the capture extra)")

from dsg_gym.cameras import look_at  # noqa: E402
from train_world.capture import load_capture  # noqa: E402
from train_world.capture.compare import compare_captures  # noqa: E402
from train_world.capture.marker import MarkerObservation, detect_marker, marker_scale, triangulate  # noqa: E402
from train_world.capture.photo_capture import build_capture  # noqa: E402
from train_world.capture.photos import PhotoCaptureError  # noqa: E402
from train_world.cli import capture as capture_cli  # noqa: E402
from train_world.cli import synth as synth_cli  # noqa: E402

SIZE = 0.1  # metres, the marker's black square


@pytest.fixture(scope="module")
def photos(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("marker") / "four_mixed"
    rc = synth_cli.main(["--scene", "four_mixed", "--out", str(out), "--views", "24", "--test-states", "0",
                         "--test-views", "0", "--as-photos", "--marker", str(SIZE), "--quiet"])  # fmt: skip
    assert rc == 0
    return out


def _cameras(n=6):
    K = np.array([[200.0, 0, 128], [0, 200.0, 128], [0, 0, 1]])
    eyes = [(0.6 * np.cos(a), 0.6 * np.sin(a), 0.4) for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]
    return K, [look_at(np.array(e), np.zeros(3), np.array([0, 0, 1.0])) for e in eyes]


def test_triangulation_and_scale_from_exact_corners():
    K, w2cs = _cameras()
    h = 0.03
    X = np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]]) + [0.05, 0.02, 0.0]
    obs = []
    for i, w2c in enumerate(w2cs):
        cam = (w2c[:3, :3] @ X.T + w2c[:3, 3:4]).T
        px = (K @ cam.T).T
        obs.append(MarkerObservation(f"v{i}", 0, px[:, :2] / px[:, 2:3], K, w2c))
    np.testing.assert_allclose(triangulate(np.stack([o.corners[0] for o in obs]), np.stack([K] * 6),
                                           np.stack(w2cs)), X[0], atol=1e-9)  # fmt: skip
    ms = marker_scale(obs, 0.06)  # the cameras' units are metres here: 1 m per unit
    assert abs(ms.metres_per_unit - 1.0) < 1e-9 and ms.rms_px < 1e-6 and ms.views == 6
    with pytest.raises(PhotoCaptureError, match="seen in 1 registered photo"):
        marker_scale(obs[:1], 0.06)


def test_detects_a_drawn_marker():
    img = cv2.aruco.generateImageMarker(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), 7, 60)
    page = np.full((120, 120), 255, np.uint8)
    page[30:90, 30:90] = img
    found = detect_marker(np.repeat(page[:, :, None], 3, axis=2))
    assert found is not None and found[0] == 7
    np.testing.assert_allclose(found[1].min(axis=0), [29.5, 29.5], atol=0.6)
    assert detect_marker(np.repeat(page[:, :, None], 3, axis=2), marker_id=3) is None
    assert detect_marker(np.full((64, 64, 3), 128, np.uint8)) is None


def test_marker_gives_metric_scale_within_one_percent(photos, tmp_path):
    assert (
        json.loads((photos / "ground_truth" / "scene.json").read_text())["generator"]["marker"]["size_m"]
        == SIZE
    )
    out = tmp_path / "capture"
    report = build_capture(photos, out, marker_size=SIZE, progress=False)
    assert report["units"] == "metres" and report["scale"]["source"].startswith(
        "ArUco marker DICT_4X4_50 id 0"
    )
    assert report["scale"]["marker_reprojection_rms_px"] < 0.5
    cap = load_capture(out)
    assert cap.units == "metres"
    r = compare_captures(cap, load_capture(photos / "ground_truth", ["state1", "state2"], load_depth=False))
    print(report["scale"], r["similarity_scale"])
    assert abs(r["similarity_scale"] - 1.0) < 0.01  # the estimated frame is metric to 1 %


def test_marker_errors(photos, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        capture_cli.main([str(photos), "--out", str(tmp_path / "a"), "--marker-size", "0.1", "--metres-per-unit",
                          "1", "--quiet"])  # fmt: skip
    assert e.value.code == 2 and not (tmp_path / "a").exists()
    assert "scale once" in capsys.readouterr().err
    out = tmp_path / "b"
    rc = capture_cli.main(
        [str(photos), "--out", str(out), "--marker-size", "0.1", "--marker-id", "9", "--quiet"]
    )
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert rc == 2 and err.startswith("dsg-capture: error: ") and "seen in 0 registered photo" in err
    assert not out.exists()
