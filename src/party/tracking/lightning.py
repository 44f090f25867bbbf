"""Lightning's MLflow logger bound to a stage's open run."""
from __future__ import annotations

from party.tracking.log import is_rank_zero
from party.tracking.store import _tcfg, tracking_uri


def lightning_logger(cfg, run):
    """An ``MLFlowLogger`` bound to the open run, or ``False`` (no logger) without a run.

    Pass the result straight to ``Trainer(logger=...)``. Unlike the stock logger it does
    not end the run when ``fit`` finishes (``start_run`` owns the run's status). Its
    ``save_dir`` is None for SQLite URIs: give ``ModelCheckpoint`` an explicit ``dirpath``.
    ``tracking.log_model`` (default false) uploads checkpoints as artifacts too.
    """
    run_id = getattr(getattr(run, "info", None), "run_id", None)
    if run_id is None or not is_rank_zero():
        return False
    t = _tcfg(cfg)
    return _bound_logger_cls()(experiment_name=t["experiment"], tracking_uri=tracking_uri(cfg), run_id=run_id,
                               log_model=t["log_model"])


_LOGGER_CLS = None


def _bound_logger_cls():
    global _LOGGER_CLS
    if _LOGGER_CLS is None:
        from lightning.pytorch.loggers import MLFlowLogger
        from lightning.pytorch.utilities import rank_zero_only

        class RunBoundMLFlowLogger(MLFlowLogger):
            """MLFlowLogger that logs into an existing run and leaves its status alone."""

            @rank_zero_only
            def finalize(self, status: str = "success") -> None:
                if self._initialized and self._checkpoint_callback:
                    self._scan_and_log_checkpoints(self._checkpoint_callback)

        _LOGGER_CLS = RunBoundMLFlowLogger
    return _LOGGER_CLS
