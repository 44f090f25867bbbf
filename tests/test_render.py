"""party.render: stick-figure GIF/MP4 of (T, J, 3) joints."""
from __future__ import annotations

import numpy as np
import pytest
from helpers import rest_pose, wiggle_joints
from PIL import Image

from party.render import (CENTER_COLOR, LEFT_COLOR, RIGHT_COLOR, render_comparison,
                          render_frames, render_keyframes, render_motion)


def walk(n: int, skeleton: str = "t2m") -> np.ndarray:
    m = np.repeat(rest_pose(skeleton)[None], n, 0)
    m[..., 2] += 0.03 * np.arange(n)[:, None]
    return m


def gif_info(path):
    with Image.open(path) as im:
        return im.n_frames, im.info["duration"], im.size


def test_gif_frames_duration_atomic(tmp_path):
    out = render_motion(walk(30), tmp_path / "sub" / "walk.gif", fps=20,
                        title="a person walks forward " * 6)
    assert out == tmp_path / "sub" / "walk.gif"
    n, duration, (w, h) = gif_info(out)
    assert n == 30 and duration == 50
    assert w == 320 and h % 16 == 0 and h > 320          # wrapped caption in a header
    assert [p.name for p in (tmp_path / "sub").iterdir()] == ["walk.gif"]  # no temp left


def test_mp4_is_h264_readable(tmp_path):
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    out = render_motion(wiggle_joints(25), tmp_path / "m.mp4", fps=20, title="wiggle")
    reader = imageio_ffmpeg.read_frames(str(out))
    meta = next(reader)
    assert meta["fps"] == 20 and meta["size"][0] == 320 and meta["codec"].startswith("h264")
    assert sum(1 for _ in reader) == 25


def test_stride_and_max_frames_keep_duration(tmp_path):
    n, duration, _ = gif_info(render_motion(walk(100), tmp_path / "a.gif", max_frames=20))
    assert (n, duration) == (20, 250)                    # stride 5 at 20 fps
    n, duration, _ = gif_info(render_motion(walk(100), tmp_path / "b.gif", stride=3))
    assert (n, duration) == (34, 150)
    with pytest.raises(ValueError, match="stride"):
        render_motion(walk(10), tmp_path / "c.gif", stride=0)


def test_comparison_panels_and_lengths(tmp_path):
    gt, rec = walk(40), walk(25) + 0.05
    out = render_comparison([gt, rec], ["ground truth", "reconstruction"], tmp_path / "c.gif",
                            title="comparison")
    n, _, (w, h) = gif_info(out)
    assert n == 40 and w == 640                          # shorter motion holds its last pose
    with pytest.raises(ValueError, match="2 titles for 3 motions"):
        render_comparison([gt, rec, gt], ["a", "b"], tmp_path / "d.gif")


def test_kit_skeleton(tmp_path):
    n, _, _ = gif_info(render_motion(walk(8, "kit"), tmp_path / "k.gif", skeleton_name="kit",
                                     fps=12.5))
    assert n == 8


@pytest.mark.parametrize("bad, match", [
    (np.zeros((10, 21, 3)), r"shape \(10, 21, 3\), expected \(T, 22, 3\)"),
    (np.zeros((10, 66)), r"expected \(T, 22, 3\)"),
    (np.zeros((0, 22, 3)), "no frames"),
    (np.full((5, 22, 3), np.nan), "non-finite joint positions in 5 frame"),
])
def test_bad_motion_is_a_clear_error(tmp_path, bad, match):
    path = tmp_path / "bad.gif"
    with pytest.raises(ValueError, match=match) as e:
        render_motion(bad, path)
    assert "bad.gif" in str(e.value)
    assert not any(tmp_path.iterdir())


def test_bad_suffix_skeleton_fps(tmp_path):
    with pytest.raises(ValueError, match=r"unsupported suffix '\.avi'"):
        render_motion(walk(5), tmp_path / "x.avi")
    with pytest.raises(ValueError, match="unknown skeleton"):
        render_motion(walk(5), tmp_path / "x.gif", skeleton_name="smplx")
    with pytest.raises(ValueError, match="fps"):
        render_motion(walk(5), tmp_path / "x.gif", fps=0)


def _mask(frame: np.ndarray, hex_color: str) -> np.ndarray:
    rgb = np.array([int(hex_color[i:i + 2], 16) for i in (1, 3, 5)])
    return np.abs(frame.astype(int) - rgb).sum(-1) < 60


def test_y_up_and_sides_not_mirrored():
    """The head is on top, feet at the bottom; facing the camera (+z), the body's left
    (+x in HumanML3D, red) appears on the viewer's right."""
    pose = rest_pose("t2m")[None]
    frame = next(render_frames([pose]))
    left, right, center = (_mask(frame, c) for c in (LEFT_COLOR, RIGHT_COLOR, CENTER_COLOR))
    rows = lambda m: np.nonzero(m)[0]   # noqa: E731
    cols = lambda m: np.nonzero(m)[1]   # noqa: E731
    assert left.sum() > 50 and right.sum() > 50 and center.sum() > 20
    assert rows(center).min() < min(rows(left).min(), rows(right).min())      # head on top
    assert max(rows(left).max(), rows(right).max()) > rows(center).max()      # feet at bottom
    assert cols(left).mean() > cols(right).mean() + 5


def test_view_is_a_rotation_facing_the_body():
    """World -> plot mapping is a proper rotation (no mirror) taking y to up, and the default
    camera sits in front of a body facing +z (the HumanML3D canonical facing)."""
    import inspect

    from party.render import _Scene, _to_plot
    R = np.stack([_to_plot(e) for e in np.eye(3)], axis=1)   # columns: images of x, y, z
    assert np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(R @ [0, 1, 0], [0, 0, 1])
    params = inspect.signature(_Scene).parameters
    elev, azim = np.radians(params["elev"].default), np.radians(params["azim"].default)
    cam_plot = [np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim), np.sin(elev)]
    cam_world = R.T @ cam_plot
    assert cam_world[2] > 0.5 and cam_world[1] > 0    # in front (+z) and above


def test_keyframes_sheet_rows_and_poses():
    """One row per frame asked for, the header only over the first; each row shows the pose of
    its own frame (a raised left wrist appears in the second row only); bad frames are refused."""
    still = np.repeat(rest_pose("t2m")[None], 10, 0)
    moving = still.copy()
    moving[5:, 20, 1] += 0.8                        # left wrist raised from frame 5
    sheet = render_keyframes([still, moving], ["a", "b"], [0, 7], title="caption", panel_px=160)
    plain = next(render_frames([still, moving], panel_px=160))
    assert sheet.shape[1] == 320 and sheet.dtype == np.uint8
    assert sheet.shape[0] > 2 * plain.shape[0] - 1              # a header over the first row
    first, last = sheet[:sheet.shape[0] - plain.shape[0]], sheet[-plain.shape[0]:]
    red_top = lambda img: np.nonzero(_mask(img[-160:, 160:], LEFT_COLOR))[0].min()   # noqa: E731
    assert red_top(first) == red_top(plain)            # frame 0: the rest pose, as render_frames draws it
    assert red_top(last) < red_top(plain) - 5          # frame 7: the raised wrist, higher up
    with pytest.raises(ValueError, match="within"):
        render_keyframes([still], [], [10])
    with pytest.raises(ValueError, match="titles"):
        render_keyframes([still], ["a", "b"], [0])
