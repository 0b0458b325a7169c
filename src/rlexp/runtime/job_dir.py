"""The dir Hydra gives a job, for any path. Hydra keeps the resolved dir in
``hydra.runtime.output_dir`` as a plain string, which OmegaConf then reads as an interpolation: a
run dir whose name holds ``${`` (``outputs/lr_${x}``, a dir renamed by hand, ``hydra.run.dir`` given
as ``'...\\${x}'``) broke Hydra's log file and ``HydraConfig.get().runtime.output_dir``. rlexp reads
the dir from ``hydra.run.dir`` (or ``hydra.sweep.dir`` / ``subdir``), resolved once, through the
``rlexp_job_dir`` resolver that the log file of conf/config.yaml names."""

from __future__ import annotations

import os

RESOLVER = "rlexp_job_dir"


def job_dir() -> str:
    """The absolute dir of the Hydra job running now (its run dir)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    hc = HydraConfig.get()
    if hc.mode == RunMode.MULTIRUN:
        return os.path.abspath(os.path.join(str(hc.sweep.dir), str(hc.sweep.subdir)))
    return os.path.abspath(str(hc.run.dir))


def register_resolver() -> None:
    """``${rlexp_job_dir:}`` for the configs (idempotent); its value is never re-resolved."""
    from omegaconf import OmegaConf

    if not OmegaConf.has_resolver(RESOLVER):
        OmegaConf.register_new_resolver(RESOLVER, job_dir, use_cache=False)
