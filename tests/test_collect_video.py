"""dsg-collect --video N: the first N episodes of the dataset as videos."""

import json

from PIL import Image

from dsg_gym.cli.collect import main

KW = {"width": 16, "height": 16, "obs": ["poses"], "render_width": 32, "render_height": 32}


def test_collect_writes_videos_of_the_first_episodes(tmp_path, capsys):
    args = ["--episodes", "2", "--max-episode-steps", "3", "--seed", "4", "--out", str(tmp_path), "--no-progress",
            "--env-kwargs", json.dumps(KW)]  # fmt: skip
    assert main([*args, "--video", "3"]) == 2  # more videos than episodes: refused before anything runs
    assert "--video" in capsys.readouterr().err and not any(tmp_path.iterdir())
    assert main([*args, "--video", "1"]) == 0
    assert "videos: 1 in" in capsys.readouterr().out
    vids = sorted((tmp_path / "dsgworld" / "random-v0" / "videos").iterdir())
    assert [v.stem for v in vids] == ["episode_0000"]
    if vids[0].suffix == ".gif":
        with Image.open(vids[0]) as im:
            assert im.n_frames == 4 and im.size[1] == 32  # T + 1 frames of the render() size
    else:
        assert vids[0].suffix == ".mp4" and vids[0].stat().st_size > 0
