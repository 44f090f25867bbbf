"""Stick-figure rendering of joint trajectories to GIF or MP4.

``render_motion(joints, path)`` draws one motion; ``render_comparison([a, b], titles, path)``
draws several side by side (e.g. ground truth vs reconstruction) with shared axes, so
drift and floating show up; ``render_keyframes`` draws them at a few frames as one still
image. Joints are ``(T, J, 3)`` in metres with **y up** (the HumanML3D / KIT convention).
The figure is drawn along the skeleton's kinematic chains (``party.motion.skeleton``): left
side red, right side blue, spine/head grey, over a ground plane with the root's ground
trajectory.

The output format follows the suffix: ``.gif`` (Pillow) or ``.mp4`` (H.264 through the
ffmpeg binary shipped by ``imageio-ffmpeg``). Frames are rendered with blitting (static
scene drawn once, only the moving artists redrawn per frame) on a pyplot-free Agg canvas,
so this is safe in worker processes and notebooks. Files are written to a temporary name
in the target directory and renamed into place.
"""
from __future__ import annotations

import math
import os
import textwrap
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from party.io import atomic_path
from party.motion.skeleton import get_skeleton

FORMATS = (".gif", ".mp4")
LEFT_COLOR = "#d62728"
RIGHT_COLOR = "#1f77b4"
CENTER_COLOR = "#404040"
TRAJ_COLOR = "#ff7f0e"
_TITLE_PT = 10
_PANEL_TITLE_PT = 9

#: keyword arguments of every Matplotlib call of the project that draws a caption, a title or a
#: label: the text as given. Matplotlib would otherwise read text between two ``$`` as mathtext, so
#: a caption such as ``a man walks $^$ fast`` raised ValueError, and ``costs $5 or $6`` lost its
#: dollar signs. (Legends take no keyword for it: ``plain_legend``.)
PLAIN_TEXT = {"parse_math": False}


def plain_legend(legend):
    """``legend``'s texts drawn as given (see ``PLAIN_TEXT``); returns the legend."""
    for t in legend.get_texts():
        t.set_parse_math(False)
    return legend


def _check_motions(motions: Sequence, skeleton_name: str, where: str) -> list[np.ndarray]:
    skel = get_skeleton(skeleton_name)
    if len(motions) == 0:
        raise ValueError(f"{where}: no motion given")
    out = []
    for i, m in enumerate(motions):
        a = np.asarray(m, dtype=np.float64)
        if a.ndim != 3 or a.shape[1:] != (skel.n_joints, 3):
            raise ValueError(f"{where}: motion {i} has shape {tuple(a.shape)}, expected "
                             f"(T, {skel.n_joints}, 3) for skeleton {skeleton_name!r}")
        if a.shape[0] == 0:
            raise ValueError(f"{where}: motion {i} has no frames")
        if not np.isfinite(a).all():
            bad = int((~np.isfinite(a)).any(axis=(1, 2)).sum())
            raise ValueError(f"{where}: motion {i} has non-finite joint positions in {bad} frame(s)")
        out.append(a)
    return out


def _chain_colors(skeleton_name: str) -> list[str]:
    skel = get_skeleton(skeleton_name)
    colors = []
    for chain in skel.kinematic_chain:
        names = [skel.joint_names[j] for j in chain]
        if any(n.startswith("l_") for n in names):
            colors.append(LEFT_COLOR)
        elif any(n.startswith("r_") for n in names):
            colors.append(RIGHT_COLOR)
        else:
            colors.append(CENTER_COLOR)
    return colors


def _to_plot(a: np.ndarray) -> np.ndarray:
    """World (x, y up, z) -> matplotlib (X=x, Y=-z, Z=y): a proper rotation, no mirroring."""
    return np.stack([a[..., 0], -a[..., 2], a[..., 1]], axis=-1)


class _Scene:
    """One figure with a panel per motion; ``frame(t)`` returns an (H, W, 3) uint8 image."""

    def __init__(self, motions: list[np.ndarray], titles: Sequence[str], skeleton_name: str,
                 title: str, panel_px: int = 320, dpi: int = 80, elev: float = 20.0,
                 azim: float = -70.0, zoom: float = 1.2):
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from mpl_toolkits.mplot3d.art3d import Poly3DCollection

        self.motions = [_to_plot(m) for m in motions]
        n = len(motions)
        skel = get_skeleton(skeleton_name)
        chains = [list(c) for c in skel.kinematic_chain]
        colors = _chain_colors(skeleton_name)

        # header: wrapped figure title + wrapped panel titles, sized in pixels
        px_per_pt = dpi / 72.0
        width = n * panel_px
        chars = max(10, int(width / (_TITLE_PT * px_per_pt * 0.6)))
        head = textwrap.fill(title, chars) if title else ""
        panel_chars = max(8, int(panel_px / (_PANEL_TITLE_PT * px_per_pt * 0.6)))
        sub = [textwrap.fill(t, panel_chars) if t else "" for t in titles]
        head_lines = head.count("\n") + 1 if head else 0
        sub_lines = max((s.count("\n") + 1 for s in sub if s), default=0)
        head_px = head_lines * _TITLE_PT * 1.35 * px_per_pt
        header = int(math.ceil(head_px + sub_lines * _PANEL_TITLE_PT * 1.35 * px_per_pt))
        header += 8 if header else 0
        height = panel_px + header
        height += (-height) % 16  # H.264 / yuv420p want macro-block-aligned frames
        self.size = (width, height)

        self.fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi)
        self.canvas = FigureCanvasAgg(self.fig)
        if head:
            self.fig.text(0.5, 1 - 3 / height, head, ha="center", va="top", fontsize=_TITLE_PT, **PLAIN_TEXT)

        # shared bounds over all motions, equal scale on all axes, fitted to the data
        allp = np.concatenate([m.reshape(-1, 3) for m in self.motions])
        lo, hi = allp.min(0), allp.max(0)
        floor = lo[2]
        cx, cy = (lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2
        rx, ry = max((hi[0] - lo[0]) / 2 + 0.3, 0.75), max((hi[1] - lo[1]) / 2 + 0.3, 0.75)
        h = max(hi[2] - floor, 1.0) * 1.05
        grid = 0.5 * math.ceil(max(rx, ry) / 5.0)  # floor grid: 0.5 m cells, coarser when far

        self.axes, self.dynamic = [], []
        top = panel_px / height
        for i, m in enumerate(self.motions):
            ax = self.fig.add_axes([i / n, 0.0, 1.0 / n, top], projection="3d",
                                   computed_zorder=False)
            ax.set_xlim(cx - rx, cx + rx)
            ax.set_ylim(cy - ry, cy + ry)
            ax.set_zlim(floor, floor + h)
            ax.set_box_aspect((2 * rx, 2 * ry, h), zoom=zoom)
            ax.view_init(elev=elev, azim=azim)
            ax.set_axis_off()
            corners = [(cx - rx, cy - ry, floor), (cx + rx, cy - ry, floor),
                       (cx + rx, cy + ry, floor), (cx - rx, cy + ry, floor)]
            ax.add_collection3d(Poly3DCollection([corners], facecolor="#e8e8e8",
                                                 edgecolor="#bbbbbb"))
            for gx in np.arange(np.ceil((cx - rx) / grid), np.floor((cx + rx) / grid) + 1) * grid:
                ax.plot([gx, gx], [cy - ry, cy + ry], [floor, floor], color="#d0d0d0", lw=0.6)
            for gy in np.arange(np.ceil((cy - ry) / grid), np.floor((cy + ry) / grid) + 1) * grid:
                ax.plot([cx - rx, cx + rx], [gy, gy], [floor, floor], color="#d0d0d0", lw=0.6)
            root = m[:, 0]
            ax.plot(root[:, 0], root[:, 1], np.full(len(root), floor), color=TRAJ_COLOR,
                    lw=0.8, alpha=0.35)
            if i < len(sub) and sub[i]:
                self.fig.text((i + 0.5) / n, 1 - (5 + head_px) / height, sub[i], ha="center",
                              va="top", fontsize=_PANEL_TITLE_PT, **PLAIN_TEXT)
            traj, = ax.plot([], [], [], color=TRAJ_COLOR, lw=1.6, animated=True)
            lines = [ax.plot([], [], [], color=c, lw=2.2, marker="o", markersize=2.0,
                             solid_capstyle="round", animated=True)[0] for c in colors]
            self.axes.append(ax)
            self.dynamic.append((m, floor, traj, list(zip(chains, lines))))
        self.counter = self.fig.text(0.01, 0.01, "", fontsize=7, color="#666666", animated=True, **PLAIN_TEXT)
        self.canvas.draw()
        self.background = self.canvas.copy_from_bbox(self.fig.bbox)
        w, h = self.canvas.get_width_height()
        if (w, h) != self.size:
            raise RuntimeError(f"canvas is {w}x{h}, expected {self.size[0]}x{self.size[1]}")

    def frame(self, t: int, n_frames: int) -> np.ndarray:
        self.canvas.restore_region(self.background)
        for ax, (m, floor, traj, chain_lines) in zip(self.axes, self.dynamic):
            k = min(t, len(m) - 1)  # shorter motions hold their last pose
            root = m[: k + 1, 0]
            traj.set_data_3d(root[:, 0], root[:, 1], np.full(len(root), floor))
            ax.draw_artist(traj)
            for chain, line in chain_lines:
                p = m[k, chain]
                line.set_data_3d(p[:, 0], p[:, 1], p[:, 2])
                ax.draw_artist(line)
        self.counter.set_text(f"{t + 1}/{n_frames}")
        self.fig.draw_artist(self.counter)
        return np.asarray(self.canvas.buffer_rgba())[..., :3].copy()


def _frame_indices(n: int, stride: int, max_frames: int | None) -> tuple[list[int], int]:
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    if max_frames is not None:
        if max_frames < 1:
            raise ValueError(f"max_frames must be >= 1, got {max_frames}")
        stride = max(stride, math.ceil(n / max_frames))
    return list(range(0, n, stride)), stride


def render_frames(motions: Sequence, titles: Sequence[str] = (), skeleton_name: str = "t2m",
                  title: str = "", stride: int = 1, max_frames: int | None = None,
                  **view) -> Iterator[np.ndarray]:
    """Yield (H, W, 3) uint8 frames of the motions drawn side by side.

    ``view``: ``panel_px`` (panel size, default 320), ``dpi`` (80), ``elev`` (20), ``azim``
    (-70: front-left view of a body facing +z), ``zoom`` (1.2).
    """
    motions = _check_motions(motions, skeleton_name, "render")
    if titles and len(titles) != len(motions):
        raise ValueError(f"render: {len(titles)} titles for {len(motions)} motions")
    n = max(len(m) for m in motions)
    idx, _ = _frame_indices(n, stride, max_frames)
    scene = _Scene(motions, list(titles), skeleton_name, title, **view)
    for t in idx:
        yield scene.frame(t, n)


def render_comparison(motions: Sequence, titles: Sequence[str], path: str | os.PathLike,
                      skeleton_name: str = "t2m", fps: float = 20, title: str = "",
                      stride: int = 1, max_frames: int | None = None, **view) -> Path:
    """Render motions side by side (shared axes) to ``path`` (.gif or .mp4); returns the path.

    Motions of different lengths are allowed (shorter ones hold their last pose). ``stride``
    keeps every k-th frame; ``max_frames`` raises the stride so at most that many frames are
    written. The playback rate is ``fps / stride`` so the clip keeps its real duration.
    ``view`` options as in ``render_frames``.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise ValueError(f"render {path}: unsupported suffix {path.suffix!r}, use one of {FORMATS}")
    if fps <= 0:
        raise ValueError(f"render {path}: fps must be > 0, got {fps}")
    motions = _check_motions(motions, skeleton_name, f"render {path}")
    if len(titles) not in (0, len(motions)):
        raise ValueError(f"render {path}: {len(titles)} titles for {len(motions)} motions")
    n = max(len(m) for m in motions)
    idx, stride = _frame_indices(n, stride, max_frames)
    out_fps = fps / stride
    scene = _Scene(motions, list(titles), skeleton_name, title, **view)
    frames = (scene.frame(t, n) for t in idx)

    with atomic_path(path, suffix=".tmp" + suffix) as tmp:  # ffmpeg picks the container by suffix
        if suffix == ".gif":  # one palette for all frames, from a few sample frames
            samples = [scene.frame(t, n) for t in sorted({idx[0], idx[len(idx) // 2], idx[-1]})]
            _write_gif(tmp, frames, samples, out_fps)
        else:
            _write_mp4(tmp, frames, scene.size, out_fps)
    return path


def render_keyframes(motions: Sequence, titles: Sequence[str], frames: Sequence[int],
                     skeleton_name: str = "t2m", title: str = "", **view) -> np.ndarray:
    """A contact sheet: the motions side by side (shared axes) at each of ``frames``, one row per
    frame, stacked top to bottom; the first row carries ``title`` and the panel ``titles``.
    Returns an (H, W, 3) uint8 image. ``view`` options as in ``render_frames``."""
    motions = _check_motions(motions, skeleton_name, "render_keyframes")
    if titles and len(titles) != len(motions):
        raise ValueError(f"render_keyframes: {len(titles)} titles for {len(motions)} motions")
    n = max(len(m) for m in motions)
    if not frames or any(not 0 <= t < n for t in frames):
        raise ValueError(f"render_keyframes: frames {list(frames)} must be non-empty and within [0, {n})")
    head = _Scene(motions, list(titles), skeleton_name, title, **view)
    rows = [head.frame(frames[0], n)]
    if len(frames) > 1:
        plain = _Scene(motions, [], skeleton_name, "", **view)
        rows += [plain.frame(t, n) for t in frames[1:]]
    return np.concatenate(rows, axis=0)


def render_motion(joints, path: str | os.PathLike, skeleton_name: str = "t2m", fps: float = 20,
                  title: str = "", **kw) -> Path:
    """Render one (T, J, 3) motion to ``path`` (.gif or .mp4); see ``render_comparison``."""
    return render_comparison([joints], [], path, skeleton_name=skeleton_name, fps=fps,
                             title=title, **kw)


def _write_gif(path: Path, frames: Iterator[np.ndarray], samples: list[np.ndarray],
               fps: float) -> None:
    from PIL import Image

    # a shared palette makes quantising cheap and lets Pillow store only changed regions
    palette = Image.fromarray(np.concatenate(samples, axis=0)).quantize(
        colors=64, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    images = [Image.fromarray(f).quantize(palette=palette, dither=Image.Dither.NONE)
              for f in frames]
    duration = max(20, int(round(1000.0 / fps)))  # GIF delays are 10 ms units, >= 20 ms
    images[0].save(path, format="GIF", save_all=True, append_images=images[1:],
                   duration=duration, loop=0)


def _write_mp4(path: Path, frames: Iterator[np.ndarray], size: tuple[int, int], fps: float) -> None:
    try:
        import imageio_ffmpeg
    except ImportError as e:  # pragma: no cover - a declared dependency
        raise RuntimeError(f"render {path}: MP4 needs imageio-ffmpeg ({e})") from e
    writer = imageio_ffmpeg.write_frames(str(path), size, fps=fps, codec="libx264",
                                         pix_fmt_in="rgb24", pix_fmt_out="yuv420p",
                                         macro_block_size=16, ffmpeg_log_level="error",
                                         output_params=["-movflags", "+faststart"])
    writer.send(None)
    try:
        for f in frames:
            writer.send(np.ascontiguousarray(f))
    finally:
        writer.close()


def figure_png(fig, dpi: float) -> bytes:
    """A matplotlib figure as PNG bytes, the figure closed (report charts; notebooks show them with
    ``IPython.display.Image``, which works whatever matplotlib backend the kernel runs)."""
    import io

    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    return buf.getvalue()
