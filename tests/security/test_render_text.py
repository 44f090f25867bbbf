"""Texts are drawn as given: a caption with ``$`` signs is not Matplotlib mathtext (which raised
ValueError on ``a man walks $^$ fast`` in ``generate``, the evaluation report and video logging)."""
import numpy as np
from helpers import wiggle_joints

TEXT = "a man walks $^$ fast"


def _title_strip(width: int, height: int, text: str) -> np.ndarray:
    """The top rows of a blank frame of that size with ``text`` drawn where the renderer draws its
    title, the dollar signs escaped (Matplotlib's literal ``$``)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width / 80, height / 80), dpi=80)
    canvas = FigureCanvasAgg(fig)
    fig.text(0.5, 1 - 3 / height, text.replace("$", r"\$"), ha="center", va="top", fontsize=10)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3][:16].copy()


def test_a_title_with_dollar_signs_renders_and_shows_them(tmp_path):
    from party.render import render_frames, render_motion

    joints = wiggle_joints(12, seed=1)
    frame = next(render_frames([joints], title=TEXT, max_frames=1))
    h, w = frame.shape[:2]
    strip = frame[:16]
    assert (strip < 128).any()                                       # the title is drawn
    assert np.array_equal(strip, _title_strip(w, h, TEXT))          # as the words, dollar signs and all
    path = render_motion(joints, tmp_path / "t.gif", title=TEXT, max_frames=2)
    assert path.stat().st_size > 0
    frames = list(render_frames([joints, joints], titles=["$x$ panel", "costs $5 or $6"], title=TEXT,
                                max_frames=1))
    assert len(frames) == 1


def test_figures_with_dollar_signs_in_their_texts(tmp_path):
    """The generator's training figures: a title from a caption, parts named as given."""
    from party.generator.figures import gate_figure
    from party.render import figure_png

    png = figure_png(gate_figure({"arms": [0.25, 0.75], "$legs": [0.5, 0.5]}, f"step 3: {TEXT}"), dpi=40)
    assert png.startswith(b"\x89PNG")
