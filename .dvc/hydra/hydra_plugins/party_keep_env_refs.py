"""Imported by DVC's Hydra composition (``dvc exp run -S``; ``hydra.plugins_path`` in ``.dvc/config``)
before it resolves ``conf/`` into the ``params.yaml`` it commits with the experiment: every
``${oc.env:NAME}`` (with its default, if any) stays a reference there, as ``party params`` writes it
(docs/tracking.md, "Secrets"), so no secret from the environment lands in the experiment's commit or
in its runs' params. A stage resolves the references from its own environment. Self-contained: DVC
may run from an interpreter without the party package."""
from omegaconf import OmegaConf

_UNSET = object()


def _reference(key: str, default=_UNSET) -> str:
    if default is _UNSET:
        return "${oc.env:" + key + "}"
    if default is None:
        return "${oc.env:" + key + ",null}"
    quoted = str(default).replace("\\", "\\\\").replace("'", "\\'")
    return "${oc.env:" + key + ",'" + quoted + "'}"


OmegaConf.register_new_resolver("oc.env", _reference, replace=True)
