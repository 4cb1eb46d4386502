"""dsg-synth --as-photos: what a phone adds to the rendered images."""

import numpy as np
import pytest

from train_world.cli import synth as synth_cli
from train_world.synth.photos import degrade_photo, generate_photo_capture


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


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--photo-exposure", "0.1"], "--as-photos"),
        (["--as-photos", "--photo-exposure", "1.5"], "[0, 1)"),
        (["--photo-scale", "2"], "--as-photos"),
        (["--as-photos", "--photo-scale", "0"], "--photo-scale"),
    ],
)
def test_photo_options_need_as_photos_and_sane_values(tmp_path, capsys, args, says):
    with pytest.raises(SystemExit):
        synth_cli.main(["--scene", "two_blocks", "--out", str(tmp_path / "x"), *args])
    assert says in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_photo_scale_must_be_an_integer(tmp_path):
    with pytest.raises(ValueError, match="scale"):
        generate_photo_capture("two_blocks", tmp_path / "x", scale=2.5)
    assert not (tmp_path / "x").exists()


def test_larger_photos_show_the_ground_truths_views(tmp_path):
    """Photos at 2x are the same views as the ground truth: box-averaged back to its size they match it to
    within JPEG's error, the masks are the ground truth's ids at twice the size, and the ground truth is the
    one a 1x photo capture of the same seed gets."""
    from PIL import Image

    from train_world.synth.generate import GenerateConfig

    cfg = GenerateConfig(width=24, height=20, views=3, test_views=1, test_states=1, progress=False)
    one = generate_photo_capture("two_blocks", tmp_path / "one", cfg)
    two = generate_photo_capture("two_blocks", tmp_path / "two", cfg, scale=2)
    assert not (two / ".photo_source").exists()
    for rel in ("scene.json", "state1/transforms.json", "state2/images/0002.png", "test_0/masks/0000.png"):
        assert (one / "ground_truth" / rel).read_bytes() == (two / "ground_truth" / rel).read_bytes()
    for state in ("state1", "state2"):
        for i in range(3):
            truth = np.asarray(
                Image.open(two / "ground_truth" / state / "images" / f"{i:04d}.png").convert("RGB")
            )
            photo = np.asarray(Image.open(two / state / "images" / f"{i:04d}.jpg"))
            assert photo.shape == (40, 48, 3)
            down = photo.astype(float).reshape(20, 2, 24, 2, 3).mean(axis=(1, 3))
            assert np.abs(down - truth).mean() < 3.0  # a different view would be off by tens of levels
            ids = np.asarray(Image.open(two / state / "masks" / f"{i:04d}.png"))
            truth_ids = np.asarray(Image.open(two / "ground_truth" / state / "masks" / f"{i:04d}.png"))
            assert ids.shape == (40, 48) and set(np.unique(ids)) == set(np.unique(truth_ids))
            assert (ids[::2, ::2] == truth_ids).mean() > 0.9
