"""The stage skeleton: what every ``party <stage>`` does around its own work.

    from party.stage import stage

    @stage("evaluate")
    def run(cfg, run_):              # run_: the stage's open MLflow run (or a NullRun)
        ...                          # the work: wire config to library calls
        return metrics               # a dict; the Hydra app returns it

``run(cfg)`` then, in order:

1. checks the config against the schema (``party.schema.validate``: a wrong type or an
   unknown key fails here, naming the key);
2. seeds Python, NumPy and torch from ``seed``;
3. opens the stage's MLflow run *before* the work (``party.tracking.start_run``; a no-op
   run when ``tracking.enabled`` is false or on a non-zero DDP rank);
4. runs the body; if it raises, the run ends FAILED (KILLED on Ctrl-C or SIGTERM) carrying
   the error as the ``party.error`` tag and the traceback as ``error.txt``; a run this stage
   left RUNNING when its process was killed (``kill -9``) is marked KILLED at the next start;
5. logs ``stage/seconds`` and prints one summary line;
6. returns the body's metrics dict.

``run_name`` and ``tags`` may be callables of the config (e.g. the stream a run trains).
The progress flag is ``cfg.progress``; stages pass it to their bars.
"""
from __future__ import annotations

import functools
import random
import time
import traceback
from typing import Any, Callable, Mapping

from party import tracking
from party.lifecycle import terminate_on_sigterm
from party.schema import validate

Body = Callable[[Any, Any], Any]


def seed_all(seed: int) -> None:
    """Seed Python's, NumPy's and torch's global generators."""
    import numpy as np
    import torch

    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def _value(x, cfg):
    return x(cfg) if callable(x) else x


def stage(name: str, run_name: str | Callable | None = None,
          tags: Mapping[str, Any] | Callable | None = None) -> Callable[[Body], Callable]:
    """Wrap ``body(cfg, run_) -> dict`` into the stage's ``run(cfg) -> dict``."""

    def deco(body: Body) -> Callable:
        @functools.wraps(body)
        def run(cfg):
            cfg = validate(cfg, "params.yaml")
            # `party params` refuses a credential typed into the config; params.yaml written otherwise
            # (`dvc exp run -S key=value`, an edit) is refused here, before any run logs it
            from omegaconf import OmegaConf

            from party.config import refuse_literal_credentials
            refuse_literal_credentials(OmegaConf.to_container(cfg, resolve=False), "params.yaml")
            seed_all(int(cfg.seed))
            rname = _value(run_name, cfg) or name
            t0 = time.time()
            with terminate_on_sigterm(), \
                    tracking.start_run(cfg, name, run_name=rname, tags=_value(tags, cfg)) as run_:
                try:
                    out = body(cfg, run_)
                except BaseException as e:
                    _record_failure(run_, e)
                    raise
                seconds = round(time.time() - t0, 1)
                run_.log_metrics({"stage/seconds": seconds})
            rid = getattr(run_.info, "run_id", None)
            print(f"[party] {rname}: done in {seconds} s" + (f" (MLflow run {rid})" if rid else ""))
            return out

        run.stage_name = name
        return run

    return deco


def _record_failure(run_, e: BaseException) -> None:
    """The error as a tag and the traceback as an artifact of the (about to fail) run."""
    if not getattr(run_.info, "run_id", None):
        return
    try:
        run_.set_tags({"party.error": f"{type(e).__name__}: {e}"[:4000]})
        run_.log_text("".join(traceback.format_exception(type(e), e, e.__traceback__)), "error.txt")
    except Exception:  # noqa: BLE001 - never hide the stage's own error behind a logging one
        pass
