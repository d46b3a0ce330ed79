"""Stick-figure previews: GIF frames, sizes and timing, PNG filmstrips, facing, stats and the CLI."""

import argparse

import numpy as np
import pytest
from PIL import Image

from dimgestor.bvh import BvhMotion, Skeleton, read_bvh, write_bvh
from dimgestor_app.render import (COLORS, facing_yaw, motion_stats, project, register, render_motion, stick_figure,
                                  world_positions)
from dimgestor.training.synthetic import synthetic_motion

POS = ["Xposition", "Yposition", "Zposition"]
ROT = ["Zrotation", "Xrotation", "Yrotation"]


def triangle_motion(amplitude=30.0, fps=30, periods=2) -> BvhMotion:
    """LeftHand slides along X from 0 to `amplitude` in 1 s and back (constant speed); the rest is still."""
    sk = Skeleton(names=["Hips", "LeftHand", "RightHand"], parents=[-1, 0, 0],
                  offsets=np.array([[0, 100, 0], [20, 0, 0], [-20, 0, 0]], float),
                  channels=[POS + ROT, ["Xposition"] + ROT, ROT])
    k = np.arange(2 * fps * periods)
    x = amplitude * np.minimum(k % (2 * fps), 2 * fps - k % (2 * fps)) / fps  # 0 .. A .. 0, A per second
    values = np.zeros((len(k), sk.num_channels))
    values[:, 1] = 100.0
    values[:, 6] = 20.0 + x
    return BvhMotion(sk, 1.0 / fps, values)


def yawed(motion: BvhMotion, degrees: float) -> BvhMotion:
    """The motion with its root turned about Y by `degrees` (root channels ZXY: Yrotation is column 5)."""
    values = motion.values.copy()
    values[:, 5] += degrees
    return BvhMotion(motion.skeleton, motion.frame_time, values)


def gif_durations(path) -> list[int]:
    with Image.open(path) as im:
        out = []
        for i in range(im.n_frames):
            im.seek(i)
            out.append(im.info["duration"])
        return out


def test_gif_has_the_subsampled_frames_size_and_real_time_delays(tmp_path):
    motion = synthetic_motion(seconds=2.0, fps=30)
    out = tmp_path / "clip.gif"
    n = render_motion(motion, out, fps=15, size=(320, 240))
    with Image.open(out) as im:
        assert (im.n_frames, im.size) == (n, (320, 240)) == (30, (320, 240))
    delays = gif_durations(out)
    assert set(delays) <= {60, 70} and sum(delays) == 2000  # 15 fps in whole centiseconds, no drift


def test_gif_start_and_seconds_select_the_frames(tmp_path):
    motion = synthetic_motion(seconds=3.0, fps=30)
    n = render_motion(motion, tmp_path / "part.gif", start_s=0.5, seconds=1.0, fps=30, size=(200, 160), views=("front",))
    assert n == 30
    with Image.open(tmp_path / "part.gif") as im:
        assert im.n_frames == 30 and im.size == (200, 160)
    with pytest.raises(ValueError, match="outside the clip"):
        render_motion(motion, tmp_path / "late.gif", start_s=3.5)


def test_png_filmstrip_has_the_size_and_draws_both_sides(tmp_path):
    motion = synthetic_motion(seconds=3.0, fps=30)
    out = tmp_path / "strip.png"
    assert render_motion(motion, out, size=(600, 320), panels=4, title="synthetic") == 4
    with Image.open(out) as im:
        assert im.size == (600, 320)
        rgb = np.asarray(im.convert("RGB")).astype(int)
    assert rgb.std() > 10  # not blank
    for side in ("left", "right"):  # bones of both sides are drawn in their colours
        colour = np.array([int(COLORS[side][i:i + 2], 16) for i in (1, 3, 5)])
        assert (np.abs(rgb - colour).sum(-1) < 30).sum() > 50


def test_bad_output_and_views_are_clear_errors(tmp_path):
    motion = synthetic_motion(seconds=1.0)
    with pytest.raises(ValueError, match=r"\.gif .* or \.png"):
        render_motion(motion, tmp_path / "x.jpg")
    with pytest.raises(ValueError, match="unknown view 'top'"):
        render_motion(motion, tmp_path / "x.png", views=("front", "top"))
    with pytest.raises(ValueError, match="trail joints not in the skeleton"):
        render_motion(motion, tmp_path / "x.png", trail_joints=("LeftWrist",))


def test_views_project_front_and_side():
    p = np.array([1.0, 2.0, 3.0])
    assert project(p, "front").tolist() == [1.0, 2.0]  # +X to the viewer's right
    assert project(p, "side").tolist() == [3.0, 2.0]  # seen from the character's right: forward is right


def test_end_sites_follow_their_joint():
    motion = synthetic_motion(seconds=0.5)
    sk = motion.skeleton
    pos, names, parents = world_positions(motion)
    assert pos.shape == (motion.num_frames, sk.num_joints + len(sk.end_sites), 3)
    head, tip = sk.index("Head"), names.index("Head_end")
    assert parents[tip] == head
    length = np.linalg.norm(pos[:, tip] - pos[:, head], axis=-1)
    np.testing.assert_allclose(length, np.linalg.norm(sk.end_sites[head]), atol=1e-9)
    np.testing.assert_allclose(pos[:, : sk.num_joints], world_positions(motion, end_sites=False)[0])


@pytest.mark.parametrize("degrees", [90.0, -135.0])
def test_face_camera_turns_the_clip_to_face_the_viewer(degrees):
    motion = synthetic_motion(seconds=1.0)
    turned = yawed(motion, degrees)
    pos, names, _ = world_positions(turned)
    assert np.degrees(facing_yaw(pos, names)) == pytest.approx(degrees + np.degrees(facing_yaw(*world_positions(motion)[:2])), abs=1.0)
    fig = stick_figure(turned)
    left, right = fig.names.index("LeftArm"), fig.names.index("RightArm")
    shoulders = fig.positions[:, left] - fig.positions[:, right]
    assert (shoulders[:, 0] > 0.9 * np.linalg.norm(shoulders, axis=-1)).all()  # character's left on the viewer's right


def test_fingers_are_thin_and_hands_trail():
    motion = synthetic_motion(seconds=0.5)
    fig = stick_figure(motion)
    thin = {fig.names[c] for (p, c), t in zip(fig.bones, fig.thin) if t}
    assert thin == {"LeftHand_end", "RightHand_end"}
    assert [fig.names[j] for j in fig.trails] == ["LeftHand", "RightHand"]
    assert fig.head == (fig.names.index("Head"), fig.names.index("Head_end"))


def test_motion_stats_of_a_known_motion():
    A = 30.0
    s = motion_stats(triangle_motion(A))
    assert s["hand_travel"]["LeftHand"] == pytest.approx(A / 2)  # mean at A/2; extremes 0 and A
    assert s["hand_travel"]["RightHand"] == pytest.approx(0.0)
    assert s["max_joint_speed"] == pytest.approx(A)  # A units per second
    assert s["max_joint_speed_joint"] == "LeftHand"
    assert s["mean_hand_speed"]["LeftHand"] == pytest.approx(A)
    assert s["joints"]["LeftHand"]["range"] == pytest.approx([A, 0.0, 0.0])
    assert s["joints"]["LeftHand"]["min"] == pytest.approx([20.0, 100.0, 0.0])


def test_motion_stats_of_the_synthetic_speaker_are_human():
    s = motion_stats(synthetic_motion(seconds=6.0))
    assert min(s["hand_travel_rel_root"].values()) > 5.0  # the hands gesture by more than a few cm
    assert s["max_joint_speed"] < 500.0  # and no joint moves faster than 5 m/s


def run_cli(argv) -> int:
    parser = argparse.ArgumentParser(prog="dimgestor")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_renders_a_bvh(tmp_path, capsys):
    bvh = tmp_path / "take.bvh"
    write_bvh(bvh, synthetic_motion(seconds=2.0))
    out = tmp_path / "out" / "take.png"
    assert run_cli(["render", str(bvh), "--out", str(out), "--seconds", "1", "--width", "400", "--height", "300"]) == 0
    assert "wrote" in capsys.readouterr().out
    with Image.open(out) as im:
        assert im.size == (400, 300)


def test_cli_bad_file_is_a_clear_error(tmp_path, capsys):
    bvh = tmp_path / "broken.bvh"
    write_bvh(bvh, synthetic_motion(seconds=0.5))
    lines = bvh.read_text().splitlines()
    lines[-3] = lines[-3].replace(lines[-3].split()[2], "oops", 1)
    bvh.write_text("\n".join(lines) + "\n")
    out = tmp_path / "x.gif"
    assert run_cli(["render", str(bvh), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and f"broken.bvh:{len(lines) - 2}: not a number: 'oops'" in err
    assert not out.exists()
    assert run_cli(["render", str(tmp_path / "missing.bvh"), "--out", str(out)]) == 2
    assert "missing.bvh: cannot read" in capsys.readouterr().err
    write_bvh(bvh, synthetic_motion(seconds=0.5))
    assert run_cli(["render", str(bvh), "--out", str(tmp_path / "x.jpg")]) == 2
    assert "x.jpg: output must be .gif (animation) or .png (filmstrip)" in capsys.readouterr().err
    assert run_cli(["render", str(bvh), "--out", str(out), "--start", "9"]) == 2
    assert "start 9 s is outside the clip" in capsys.readouterr().err


def test_zeggs_sample_renders_a_standing_speaker(zeggs_dir, tmp_path):
    motion = read_bvh(sorted(zeggs_dir.glob("*.bvh"))[0])
    short = BvhMotion(motion.skeleton, motion.frame_time, motion.values[: int(3 * motion.fps)])
    fig = stick_figure(short)
    head, toe = fig.names.index("Head"), fig.names.index("LeftToeBaseEnd")
    assert fig.positions[:, head, 1].min() > 140.0  # standing, Y up, in cm
    assert (fig.positions[:, toe, 2] > fig.positions[:, fig.names.index("LeftFoot"), 2]).mean() > 0.9  # toes toward the viewer
    assert render_motion(short, tmp_path / "zeggs.png", panels=3, size=(480, 400)) == 3
    s = motion_stats(short)
    assert max(s["hand_travel_rel_root"].values()) > 5.0


def test_matplotlib_is_imported_only_when_rendering():
    import subprocess
    import sys

    code = "import sys, dimgestor_app.render; assert 'matplotlib' not in sys.modules, 'imported eagerly'"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_cli_unwritable_output_names_the_path(tmp_path, capsys):
    bvh = tmp_path / "take.bvh"
    write_bvh(bvh, synthetic_motion(seconds=0.5))
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    assert run_cli(["render", str(bvh), "--out", str(blocker / "x.png")]) == 2
    assert f"error: {blocker}" in capsys.readouterr().err
