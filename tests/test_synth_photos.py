"""dsg-synth --as-photos: what a phone adds to the rendered images."""

import numpy as np
import pytest

from train_world.cli import synth as synth_cli
from train_world.synth.photos import degrade_photo


def _img():
    return np.random.default_rng(0).integers(20, 200, (32, 32, 3), dtype=np.uint8)


def test_clean_photos_are_unchanged():
    img = _img()
    assert degrade_photo(img, 0.0, np.random.default_rng(1)) is img


def test_exposure_gain_stays_in_its_range_and_follows_the_seed():
    img = _img()
    gains = []
    for seed in range(40):
        out = degrade_photo(img, 0.0, np.random.default_rng(seed), exposure=0.2)
        gains.append(out.astype(float).sum() / img.astype(float).sum())
        np.testing.assert_array_equal(out, degrade_photo(img, 0.0, np.random.default_rng(seed), exposure=0.2))
    assert 0.79 < min(gains) < 0.9 and 1.1 < max(gains) < 1.21  # spread over [0.8, 1.2]


def test_noise_and_exposure_together():
    img = _img()
    out = degrade_photo(img, 3.0, np.random.default_rng(2), exposure=0.1)
    assert out.dtype == np.uint8 and out.shape == img.shape and not np.array_equal(out, img)


def test_photo_options_need_as_photos(tmp_path, capsys):
    with pytest.raises(SystemExit):
        synth_cli.main(["--scene", "two_blocks", "--out", str(tmp_path / "x"), "--photo-exposure", "0.1"])
    assert "--as-photos" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        synth_cli.main(
            ["--scene", "two_blocks", "--out", str(tmp_path / "x"), "--as-photos", "--photo-exposure", "1.5"]
        )
    assert "[0, 1)" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
