"""The figures a generator logs while training: HPF attention (Fig. 5), PTG gates (Fig. 6), samples."""
import numpy as np
import torch

from party.generator.figures import TrainingFigures, attention_figure, gate_figure, gate_ratios

from .test_model import make_batch
from .tiny_spec import build


class FakeRun:
    def __init__(self):
        self.files = []

    def log_file(self, path, artifact_path=None):
        assert path.exists() and path.stat().st_size > 0
        self.files.append(f"{artifact_path}/{path.name}")


def test_attention_figure_cuts_each_stream_to_the_sample():
    model = build("party").eval()
    b = make_batch()
    maps = model.attention_maps(b)
    lens = {s: int(b["lengths"][s][0]) + 1 for s in ("holistic", "arms", "legs")}
    fig = attention_figure(maps, lens, ["arms", "legs"], "t")
    sa = fig.axes[0].images[0].get_array()
    assert sa.shape == (lens["holistic"] + 2 + lens["arms"] + lens["legs"],) * 2
    assert fig.axes[1].images[0].get_array().shape == (lens["holistic"], lens["arms"])
    # the holistic rows see no part element that is not yet generated: the cut keeps all their weight
    full = maps["self"][0].mean(0)
    assert torch.allclose(full.sum(-1), torch.ones(full.shape[0]), atol=1e-4)


def test_gate_ratios_and_figure():
    vals = {"val/gate_arms_0": 0.7, "val/gate_arms_1": 0.3, "val/gate_legs_1": 0.6, "val/gate_legs_0": 0.4,
            "val/loss": 1.0}
    r = gate_ratios(vals, ["arms", "legs"])
    assert r == {"arms": [0.7, 0.3], "legs": [0.4, 0.6]}
    fig = gate_figure(r)
    heights = sorted(round(p.get_height(), 3) for p in fig.axes[0].patches)
    assert heights == [0.3, 0.4, 0.6, 0.7]
    assert gate_ratios({"val/loss": 1.0}, ["arms"]) == {}


def test_training_figures_log_pngs_and_a_sample_gif():
    model = build("party").eval()
    run = FakeRun()
    joints = [np.random.default_rng(0).normal(size=(12, 22, 3)).astype(np.float32)]
    batch = {**make_batch(), "caption": ["a person waves"] * 4}
    cb = TrainingFigures(run, batch, lambda m: (joints, ["a person waves"]), "t2m", 20.0, 60)
    written = cb.log_figures(model, {"val/gate_arms_0": 0.5, "val/gate_arms_1": 0.5, "val/gate_arms_2": 0.0,
                                     "val/gate_legs_0": 1.0, "val/gate_legs_1": 0.0, "val/gate_legs_2": 0.0}, 40)
    assert written == run.files == ["figures/hpf_attention_step000040.png", "figures/ptg_gates_step000040.png",
                                    "samples/samples_step000040.gif"]
    hol = build("holistic").eval()                  # no HPF, no PTG, no samples: nothing to log
    run2 = FakeRun()
    assert TrainingFigures(run2, batch, None, "t2m", 20.0, 60).log_figures(hol, {}, 1) == []
