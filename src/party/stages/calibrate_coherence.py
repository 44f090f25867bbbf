"""``party calibrate_coherence``: grid σ, κ, L, τ_max, β for TC/SC (paper Tables S3-S5).

For each grid point: TC or SC of ground-truth clips of ``eval.calibrate.split``,
of corrupted clips (arms swapped in from another clip with a random phase
shift; a frozen stream), and their separation; the point with the largest
separation is recommended (SPEC §5 Decision). Writes
``<eval.calibrate.out_dir>/{calibration.json, tables.md}`` atomically.
"""

from __future__ import annotations

import logging
import time

import numpy as np
from omegaconf import DictConfig, OmegaConf

from party.evaluation.calibrate import calibrate, corrupt
from party.data.context import load_context
from party.evaluation.loading import coherence_parts, fit_sc_reference
from party.evaluation.protocol import motion_joints
from party.evaluation.report import calibration_tables
from party.io import atomic_dir, write_json, write_text
from party.stage import stage

log = logging.getLogger(__name__)


@stage("calibrate_coherence")
def run(cfg: DictConfig, run_) -> dict:
    ec = cfg.eval
    cal = OmegaConf.to_container(ec.calibrate, resolve=True)
    coh = OmegaConf.to_container(ec.coherence, resolve=True)
    t0 = time.time()
    seed = ec.seed
    rng = np.random.default_rng(seed)
    ctx = load_context(cfg)
    parts = coherence_parts(cfg, ctx)
    sc_ref = fit_sc_reference(ctx, parts, coh["reference_split"], coh["reference_max_clips"], seed)
    bank = ctx.bank(cal["split"], 2)
    ids = np.arange(len(bank))
    if cal["max_clips"] and len(ids) > cal["max_clips"]:
        ids = np.sort(rng.choice(ids, cal["max_clips"], replace=False))
    feats = [ctx.normalizer.denorm(bank.get(int(i)).numpy()) for i in ids]
    sets = {"gt": feats, **corrupt(feats, ctx.layout, rng, cal["min_shift"], cal["freeze_part"],
                                   cal["mix_mode"])}
    joints = {k: motion_joints(v, ctx.n_joints) for k, v in sets.items()}
    rows, best = calibrate(joints, parts, sc_ref, coh, cal)
    rec = {t: r["params"] for t, r in best.items()}
    out = {"dataset": ctx.index.dataset, "split": cal["split"], "n_clips": len(ids), "criterion": cal["criterion"],
           "current": {k: coh[k] for k in ("sigma", "kappa", "window", "tau_max", "beta_d", "beta_theta")},
           "recommended": rec, "rows": rows, "seconds": round(time.time() - t0, 1)}
    header = (f"## Coherence calibration: {ctx.index.dataset} / {cal['split']} ({len(ids)} clips)\n\n"
              f"Separation = {cal['criterion']} between ground truth and corrupted motions (arms from another "
              f"clip with a random phase shift >= {cal['min_shift']} frames, mix_mode={cal['mix_mode']}; "
              f"frozen {cal['freeze_part']}). "
              f"Recommended (bold): " + ("; ".join(f"{t}: {p}" for t, p in rec.items()) or "none") + "\n\n"
              + "".join(f"{t}: no grid point scores ground truth above the corrupted motions; "
                        f"no recommendation.\n\n" for t in ("S3", "S4", "S5") if t not in rec))
    tables = header + calibration_tables(rows, best)
    with atomic_dir(cal["out_dir"]) as tmp:
        write_json(tmp / "calibration.json", out)
        write_text(tmp / "tables.md", tables)
    run_.log_text(tables, "calibration_tables.md")
    run_.log_json(out, "calibration.json")
    run_.log_metrics({f"calibration/{r['table']}/" + "_".join(f"{k}{v}" for k, v in r["params"].items())
                      + f"/{m}": r[m] for r in rows for m in ("gt", "mix", "freeze", "separation")})
    log.info("coherence calibration in %.1f s\n%s", time.time() - t0, tables)
    return out
