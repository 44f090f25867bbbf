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
# # Coherence and attention
#
# Reads the coherence-level metrics `evaluate` wrote (`<eval.out_dir>/metrics.json`: TC and SC
# per source with 95% CIs, SPEC §5) and the figures the ParTY generator logged while it
# trained (its newest FINISHED `train_generator` run in MLflow): the Holistic-Part Fusion
# attention maps (paper Fig. 5) and the Part-aware Text Grounding gate selection ratios
# (Fig. 6), the latter redrawn from the run's `val/gate_<part>_<k>` metrics.
#
# On the level of TC: the paper's formula, kept exact, scores real walking well below the
# paper's 0.96 (legs move in anti-phase and the lag penalty bites); compare sources with each
# other (ground truth first), not with the paper's absolute numbers.
# With its defaults it finds the project from the working dir (the root or `notebooks/`) and its
# MLflow store as the stages do (`party.tracking.tracking_uri`); other values go in the cell
# tagged `parameters`. Open it in JupyterLab (`pip install -e .[lab]`), or from the project root
# run `jupyter execute notebooks/coherence_attention.ipynb`, `pytest --nbmake
# notebooks/coherence_attention.ipynb`, or `python notebooks/coherence_attention.py`.

# %% tags=["parameters"]
project = None        # the repository root (params.yaml, data/, mlruns/); default: found from the working dir
tracking_uri = None   # default: the project's store ($MLFLOW_TRACKING_URI, tracking.uri, tracking.dir)
method = "party"      # the generator whose figures are shown

# %%
import base64
import json
from pathlib import Path
from urllib.parse import unquote, urlparse

import matplotlib
import mlflow
import numpy as np
import pandas as pd
from IPython.display import HTML, Image, display

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from party import tracking  # noqa: E402
from party.config import open_project  # noqa: E402
from party.generator.figures import gate_figure, gate_ratios  # noqa: E402
from party.render import figure_png  # noqa: E402


root, cfg = open_project(project)   # also makes the project the working dir
metrics_file = Path(cfg.eval.out_dir) / "metrics.json"
results = json.loads(metrics_file.read_text())["results"]
print(f"{metrics_file}: sources {list(results)}")

# %% [markdown]
# ## Temporal and Spatial Coherence (paper Table 3)

# %%
rows = {s: {f"{k} {part}": d["coherence"][k][part] for k in ("tc", "sc") for part in ("mean", "ci95")}
        for s, d in results.items() if "coherence" in d}
coh = pd.DataFrame(rows).T
display(coh.round(3))
if len(coh):
    fig, ax = plt.subplots(figsize=(1.5 + 1.1 * len(coh), 3.2))
    x = np.arange(len(coh))
    for i, k in enumerate(("tc", "sc")):
        ax.bar(x + (i - 0.5) * 0.38, coh[f"{k} mean"], 0.38, yerr=coh[f"{k} ci95"], capsize=3, label=k.upper())
    ax.set_xticks(x, coh.index, rotation=20, fontsize=8)
    ax.set_ylabel("coherence (95% CI)")
    ax.legend()
    ax.set_title("TC / SC per source")
    fig.tight_layout()
    display(Image(figure_png(fig, dpi=90)))

# %% [markdown]
# ## The generator's training figures
# The newest FINISHED `train_generator` run of `method` in the project's store.

# %%
uri = tracking_uri or tracking.tracking_uri(cfg)
client = mlflow.MlflowClient(uri)
exp = client.get_experiment_by_name(cfg.tracking.experiment)
runs = client.search_runs([exp.experiment_id],
                          f"tags.`party.stage` = 'train_generator' and tags.`party.method` = '{method}' "
                          "and attributes.status = 'FINISHED'",
                          order_by=["attributes.start_time DESC"], max_results=50) if exp else []
# the newest run that trained (and so logged the figures; a sweep point reused from the cache has
# none), the pipeline's own before an ablation point (which may have HPF or PTG switched off)
trained = [r for r in runs if any(k.startswith("val/") for k in r.data.metrics)]
run = next((r for r in trained if "party.sweep" not in r.data.tags), trained[0] if trained else None)
print(f"store {uri}: " + (f"run {run.info.run_id} ({run.info.run_name})" if run else f"no finished {method} run"))


def local_artifact(run, path: str) -> Path:
    art = run.info.artifact_uri
    if art.startswith("file://"):
        return Path(unquote(urlparse(art).path)) / path
    return Path(mlflow.artifacts.download_artifacts(run_id=run.info.run_id, artifact_path=path, tracking_uri=uri))


def newest(run, prefix: str) -> str | None:
    names = sorted(f.path for f in client.list_artifacts(run.info.run_id, "figures")
                   if Path(f.path).name.startswith(prefix))
    return names[-1] if names else None


# %% [markdown]
# ### Holistic-Part Fusion attention (Fig. 5)
# Self-attention over [holistic; SPLIT; arms; SPLIT; legs] and the holistic stream's
# cross-attention to each part, on one validation sample, at the last validation.

# %%
fig_path = newest(run, "hpf_attention") if run else None
if fig_path:
    data = base64.b64encode(local_artifact(run, fig_path).read_bytes()).decode()
    display(HTML(f'<img src="data:image/png;base64,{data}" alt="{fig_path}">'))
    print(fig_path)
else:
    print("no HPF attention figure (HPF off, or no finished run)")

# %% [markdown]
# ### Part-aware Text Grounding gate selection ratios (Fig. 6)
# Per part, the mean gate weight of each of the K grounding embeddings at the last validation.

# %%
metrics = run.data.metrics if run else {}
parts = sorted({k[len("val/gate_"):].rsplit("_", 1)[0] for k in metrics if k.startswith("val/gate_")})
ratios = gate_ratios(metrics, parts)
if ratios:
    display(pd.DataFrame(ratios, index=[f"c'_{k + 1}" for k in range(len(next(iter(ratios.values()))))]).round(3))
    fig = gate_figure(ratios, f"PTG gate selection ratios ({method})")
    display(Image(figure_png(fig, dpi=90)))
else:
    print("no gate metrics (PTG off, or no finished run)")
