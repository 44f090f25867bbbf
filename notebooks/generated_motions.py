# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#       jupytext_version: 1.19.6
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Generated versus ground-truth motions
#
# Reads what the pipeline wrote: the prepared dataset (`paths.prepared`) and every generated
# run under `eval.sources.generated_dir` (`data/generated/<run>/index.json`, written by
# `party generate`). For a few test clips it plays ground truth beside every generator
# (stick figures, embedded GIFs), plots the wrist and ankle heights over time (a raised hand,
# a kick, a gait's alternation are visible there), and tables lengths and joint ranges per
# run. Everything is read from `params.yaml` of the project; nothing is trained.
# With its defaults it finds the project from the working dir (the root or `notebooks/`); other
# values go in the cell tagged `parameters`. Open it in JupyterLab (`pip install -e .[lab]`), or
# from the project root run `jupyter execute notebooks/generated_motions.ipynb`, `pytest --nbmake
# notebooks/generated_motions.ipynb`, or `python notebooks/generated_motions.py`.

# %% tags=["parameters"]
project = None      # the repository root (params.yaml, data/); default: found from the working dir
clips = 3           # test clips shown (the first by id that every generated run holds)
max_frames = 60     # frames per animation
runs = None         # generated run names to show (default: every one)

# %%
import base64

import matplotlib
import numpy as np
import pandas as pd
from IPython.display import HTML, Image, display

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from party.config import open_project  # noqa: E402
from party.data.context import load_context  # noqa: E402
from party.evaluation.html import animations, sample_clips  # noqa: E402
from party.evaluation.protocol import motion_joints  # noqa: E402
from party.evaluation.sources import GeneratedSource, discover_generated  # noqa: E402
from party.motion import get_skeleton  # noqa: E402
from party.render import figure_png  # noqa: E402


root, cfg = open_project(project)   # also makes the project the working dir
ctx = load_context(cfg)
split = cfg.generator.generate.split
folders = discover_generated("auto", cfg.eval.sources.generated_dir)
if runs:
    folders = [f for f in folders if f.name in set(runs)]
if not folders:
    raise SystemExit(f"no generated runs under {cfg.eval.sources.generated_dir}: run `dvc repro` first")
generated = [GeneratedSource(f, ctx) for f in folders]
print(f"project {root}; dataset {ctx.index.dataset}, split {split!r}; runs: {[g.name for g in generated]}")

# %% [markdown]
# ## Lengths and joint ranges per run
# Frames per generated motion against the ground truth of the same clips, and how far the
# wrists travel vertically (a run that decodes one pose shows a range near zero).

# %%
skel = get_skeleton(ctx.index.skeleton)
J = {n: i for i, n in enumerate(skel.joint_names)}
limbs = [n for n in ("l_wrist", "r_wrist", "l_ankle", "r_ankle") if n in J]
clip_by_id = {c["id"]: c for c in ctx.index.clips(split)}


def joint_stats(feats: list[np.ndarray]) -> dict:
    joints = motion_joints(feats, ctx.n_joints)
    row = {"motions": len(joints), "frames (mean)": float(np.mean([len(j) for j in joints]))}
    for n in limbs:
        row[f"{n} height range (m)"] = float(np.mean([np.ptp(j[:, J[n], 1]) for j in joints]))
    return row


rows = {}
ids = sorted(set.intersection(*(set(g.by_clip) for g in generated)) & set(clip_by_id))[:200]
rows["ground truth"] = joint_stats([ctx.store.clip_features(clip_by_id[i]) for i in ids])
for g in generated:
    rows[g.name] = joint_stats([g.by_clip[i][0][2] for i in ids])
display(pd.DataFrame(rows).T.round(3))

# %% [markdown]
# ## Side by side
# Ground truth (`real`) beside every generated run, each GIF titled with the caption it was
# generated from.

# %%
shown = sample_clips(ctx, generated, split, clips)
for caption, gif in animations(ctx, generated, shown, max_frames):
    data = base64.b64encode(gif).decode()
    display(HTML(f'<figure><img src="data:image/gif;base64,{data}" alt="{caption}">'
                 f"<figcaption>{caption}</figcaption></figure>"))

# %% [markdown]
# ## Wrist and ankle heights over time
# One row per clip, one column per limb joint: ground truth (black) and each run.

# %%
if shown:
    fig, axes = plt.subplots(len(shown), len(limbs), figsize=(3.2 * len(limbs), 2.4 * len(shown)),
                             squeeze=False)
    for r, c in enumerate(shown):
        motions = {"ground truth": ctx.store.clip_features(c)} | {g.name: g.by_clip[c["id"]][0][2] for g in generated}
        joints = dict(zip(motions, motion_joints(list(motions.values()), ctx.n_joints)))
        for k, n in enumerate(limbs):
            ax = axes[r, k]
            for name, j in joints.items():
                ax.plot(np.arange(len(j)) / ctx.index.fps, j[:, J[n], 1], label=name,
                        color="black" if name == "ground truth" else None, lw=1.6 if name == "ground truth" else 1)
            ax.set_title(f"{n}", fontsize=8)
            if k == 0:
                ax.set_ylabel(generated[0].by_clip[c["id"]][0][0][:40], fontsize=7)
    axes[0, -1].legend(fontsize=6)
    for ax in axes[-1]:
        ax.set_xlabel("s")
    fig.tight_layout()
    display(Image(figure_png(fig, dpi=90)))
