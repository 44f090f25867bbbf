"""Stage ``cache_interactions``: the interacting body parts, the interaction instruction and the
remaining text of every caption of the prepared index (SPEC-textim §3), through the backend
``interactions.backend`` (``rules`` offline, ``oracle`` the synthetic set's own actions, ``openai``
any OpenAI-compatible server), cached durably in ``interactions.cache_path`` (SQLite, not a DVC
out); then the interactive subset (SPEC-textim §1, ``party.data.subset``).

Writes (atomically) ``<interactions.out_dir>/``: ``interactions.json`` = {caption: {"parts",
"inter", "inter_tokens", "non", "fallback"}}, ``subset.json`` = {split: [clip ids], "counts",
"description"} and ``stats.json`` (hits, calls, retries, fallbacks, subset counts); logs the counts
to MLflow.
"""
from __future__ import annotations

import logging
from pathlib import Path

from omegaconf import DictConfig

from party.config import plain
from party.data.index import load_index
from party.data.subset import choose_subset
from party.io import atomic_dir, write_json
from party.stage import stage
from party.text.interactions import extract_index

log = logging.getLogger(__name__)


@stage("cache_interactions")
def run(cfg: DictConfig, run_) -> dict:
    icfg = cfg.interactions
    index = load_index(icfg.index_path)
    records, stats = extract_index(index, plain(icfg), progress=bool(cfg.progress))
    s = icfg.subset
    subset = choose_subset(index.clips(), lambda c: bool(records[c]["parts"]), n_interactive=s.n_interactive,
                           n_non_interactive=s.n_non_interactive,
                           non_interactive_ratio=float(s.non_interactive_ratio), mirror=str(s.mirror),
                           seed=int(cfg.seed))
    subset["description"] = (f"interactive subset: {subset['counts']['interactive']} clips with an interaction "
                             f"({icfg.backend}) + {subset['counts']['non_interactive']} without")
    stats = {**stats, "subset": subset["counts"]}
    counts = {k: v for k, v in stats.items() if isinstance(v, (int, float))}
    print("cache_interactions: " + ", ".join(f"{k}={v}" for k, v in counts.items())
          + f"; subset {subset['counts']['per_split']}")
    run_.log_metrics({f"interactions/{k}": v for k, v in counts.items()})
    out = Path(icfg.out_dir)
    with atomic_dir(out) as tmp:                   # every file or none
        write_json(tmp / "interactions.json", records)
        write_json(tmp / "subset.json", subset)
        write_json(tmp / "stats.json", stats)
    run_.log_json(stats, "interactions/stats.json")
    log.info("wrote %s (%d captions, %d subset clips)", out, len(records),
             sum(subset["counts"]["per_split"].values()))
    return stats
