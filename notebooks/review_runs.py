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
# # Review party runs
#
# Opens the project's MLflow store (SQLite `mlruns/mlflow.db`, artifacts in
# `mlruns/artifacts/`; see `docs/tracking.md`), lists the runs of an experiment, tables
# their metrics per stage, shows which params differ between runs of a stage (ablations),
# groups sweep children under their parent run, and plays the newest logged sample video.
# No server needed (a tracking server's URI works too). With its defaults it finds the project from the
# working dir (the root or `notebooks/`) and opens the store its stages log to
# (`party.tracking.tracking_uri`: `$MLFLOW_TRACKING_URI`, else `tracking.uri`, else
# `<project>/<tracking.dir>/mlflow.db`); other values go in the cell tagged `parameters`.
# Open it in JupyterLab (`pip install -e .[lab]`), or from the project root run
# `jupyter execute notebooks/review_runs.ipynb` (top to bottom; an error fails it),
# `pytest --nbmake notebooks/review_runs.ipynb`, or `python notebooks/review_runs.py` (tables
# printed). Only FINISHED runs are listed unless `all_statuses = True` (RUNNING, FAILED and
# KILLED runs too).

# %% tags=["parameters"]
project = None        # the repository root (params.yaml, mlruns/); default: found from the working dir
tracking_uri = None   # default: the project's store ($MLFLOW_TRACKING_URI, tracking.uri, tracking.dir)
experiment = None     # default: $PARTY_EXPERIMENT, else the project's tracking.experiment ("party")
stage = None          # only runs of this stage (tags.party.stage), e.g. "train_vqvae"
all_statuses = False  # True: also RUNNING, FAILED and KILLED runs
max_runs = 200

# %%
import base64
import os
from pathlib import Path
from urllib.parse import unquote, urlparse

import matplotlib
import mlflow
import pandas as pd
from IPython.display import HTML, Image, Video, display

from party import tracking
from party.config import open_project
from party.render import figure_png

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

cfg = None
if tracking_uri is None and project is None and os.environ.get("MLFLOW_TRACKING_URI"):
    tracking_uri = os.environ["MLFLOW_TRACKING_URI"]   # a store named outside any project
if tracking_uri is None or project is not None:
    root, cfg = open_project(project)   # also makes the project the working dir
    print("project:", root)
    tracking_uri = tracking_uri or tracking.tracking_uri(cfg)
experiment = experiment or os.environ.get("PARTY_EXPERIMENT") or (cfg.tracking.experiment if cfg else "party")
mlflow.set_tracking_uri(tracking_uri)
client = mlflow.MlflowClient(tracking_uri)
pd.set_option("display.width", 200)
pd.set_option("display.max_columns", 40)
pd.set_option("display.max_colwidth", 60)
print("store:", tracking_uri)
display(pd.DataFrame([{"experiment_id": e.experiment_id, "name": e.name,
                       "artifact_location": e.artifact_location}
                      for e in client.search_experiments()]))

# %% [markdown]
# ## Runs
# `mlflow.search_runs` returns one row per run: `params.*` (the flattened resolved config),
# `metrics.*` (last value of each metric) and `tags.*` (`party.stage`, `party.git_commit`,
# `mlflow.parentRunId`, ...).

# %%
conditions = ([f"tags.`party.stage` = '{stage}'"] if stage else []) + \
    ([] if all_statuses else ["attributes.status = 'FINISHED'"])
runs = mlflow.search_runs(experiment_names=[experiment], filter_string=" and ".join(conditions),
                          max_results=max_runs, order_by=["attributes.start_time DESC"])
print(f"{len(runs)} {'' if all_statuses else 'finished '}run(s) in experiment {experiment!r}")
base_cols = ["run_id", "tags.party.stage", "tags.mlflow.runName", "tags.party.dvc_exp_name", "status",
             "start_time", "tags.party.git_commit", "tags.party.git_dirty", "tags.party.git_changed"]
for c in ("tags.party.dvc_exp_name", "tags.party.git_changed"):   # shown even when no run has it
    if len(runs) and c not in runs.columns:
        runs[c] = None
overview = runs[[c for c in base_cols if c in runs.columns]] if len(runs) else runs
display(overview)

# %% [markdown]
# ## Metrics per stage
# One table per stage, one row per run, its metrics as columns: compare runs side by side.

# %%
metric_cols = [c for c in runs.columns if c.startswith("metrics.")]
stages = sorted(runs["tags.party.stage"].dropna().unique()) if len(runs) else []
for s in stages:
    sub = runs[runs["tags.party.stage"] == s]
    cols = [c for c in metric_cols if sub[c].notna().any()]
    table = sub.set_index("run_id")[["tags.mlflow.runName", *cols]]
    print(f"\nstage {s}: {len(sub)} run(s)")
    display(table.rename(columns=lambda c: c.removeprefix("metrics.")))

# %% [markdown]
# ## What differs between runs of a stage (ablation view)
# Params that are not identical across the runs of a stage, next to their metrics.

# %%
param_cols = [c for c in runs.columns if c.startswith("params.")]
for s in stages:
    sub = runs[runs["tags.party.stage"] == s]
    if len(sub) < 2:
        continue
    varying = [c for c in param_cols if sub[c].astype(str).nunique() > 1]
    cols = [c for c in metric_cols if sub[c].notna().any()]
    print(f"\nstage {s}: {len(varying)} param(s) differ")
    display(sub.set_index("run_id")[varying + cols].rename(
        columns=lambda c: c.split(".", 1)[1]))

# %% [markdown]
# ## Sweeps: children grouped under their parent run

# %%
if len(runs) and "tags.mlflow.parentRunId" in runs.columns:
    children = runs[runs["tags.mlflow.parentRunId"].notna()]
    for parent_id, group in children.groupby("tags.mlflow.parentRunId"):
        print(f"\nparent {parent_id}: {len(group)} child run(s)")
        display(group.set_index("run_id")[["tags.party.stage", "tags.mlflow.runName", "status",
                                           *[c for c in metric_cols if group[c].notna().any()]]])
else:
    print("no nested runs")

# %% [markdown]
# ## Ablation grids: one table and one chart per sweep
# `party vq_ablation` / `party gen_ablation` log each grid point as a child run tagged
# `party.sweep` and `party.sweep_point`; the point's params are the config it trained with.
# Rows: points; columns: the params that vary across the grid and the point's metrics; the
# chart shows `chart_metric` (with its `_ci95` as error bars when logged).

# %%
chart_metrics = ["top1", "fid", "val/mpjpe_mm", "val_loss"]   # the first one a grid logged is charted
sweep_tags = ["tags.party.sweep", "tags.party.sweep_point"]
points = runs[runs[sweep_tags].notna().all(axis=1)] if set(sweep_tags) <= set(runs.columns) else runs.iloc[0:0]
for sweep, grid in (points.groupby("tags.party.sweep") if len(points) else []):
    grid = grid.sort_values("start_time").drop_duplicates("tags.party.sweep_point", keep="last")
    varying = [c for c in param_cols if grid[c].astype(str).nunique() > 1]
    cols = [c for c in metric_cols if grid[c].notna().any()]
    table = grid.set_index("tags.party.sweep_point")[varying + cols].rename(columns=lambda c: c.split(".", 1)[1])
    print(f"\nsweep {sweep}: {len(grid)} point(s)")
    display(table)
    metric = next((m for m in chart_metrics if f"metrics.{m}" in grid.columns and grid[f"metrics.{m}"].notna().any()), None)
    if metric:
        err = grid.get(f"metrics.{metric}_ci95")
        fig, ax = plt.subplots(figsize=(1.5 + 0.9 * len(grid), 3.0))
        ax.bar(grid["tags.party.sweep_point"], grid[f"metrics.{metric}"],
               yerr=None if err is None else err.fillna(0), capsize=3)
        ax.set_ylabel(metric + (" (95% CI)" if err is not None else ""))
        ax.set_title(f"{sweep}")
        ax.tick_params(axis="x", labelrotation=30, labelsize=7)
        fig.tight_layout()
        display(Image(figure_png(fig, dpi=90)))
if not len(points):
    print("no sweep points yet (party gen_ablation / vq_ablation)")

# %% [markdown]
# ## Newest logged sample video
# Artifacts are plain files under the experiment's artifact location (`file://` URIs for the
# SQLite store: read in place); a remote server's artifacts are downloaded to a temp dir.


# %%
def find_videos(run_id: str, path: str = "") -> list[str]:
    out = []
    for f in client.list_artifacts(run_id, path):
        if f.is_dir:
            out += find_videos(run_id, f.path)
        elif f.path.lower().endswith((".gif", ".mp4")):
            out.append(f.path)
    return out


shown = False
for run_id in runs["run_id"] if len(runs) else []:
    videos = find_videos(run_id)
    if not videos:
        continue
    art_uri = client.get_run(run_id).info.artifact_uri
    if art_uri.startswith("file://"):
        local = str(Path(unquote(urlparse(art_uri).path)) / videos[0])
    else:
        local = mlflow.artifacts.download_artifacts(run_id=run_id, artifact_path=videos[0],
                                                    tracking_uri=tracking_uri)
    print(f"run {run_id}: {videos[0]} ({len(videos)} video(s) in the run)\n{local}")
    if local.lower().endswith(".gif"):   # embedded, so an exported notebook (HTML) shows the motion
        data = base64.b64encode(Path(local).read_bytes()).decode()
        display(HTML(f'<img src="data:image/gif;base64,{data}" alt="{videos[0]}">'))
    else:
        display(Video(local, embed=True))
    shown = True
    break
if not shown:
    print("no run has logged a video yet")
