"""The one place where configs become objects: ``schema`` types each settings node, ``checks`` refuses bad
values across them, ``components`` finds the classes the yaml files name, ``build`` assembles a run's parts,
``restore`` a checkpoint's model,
``record`` a checkpoint's model record and the config rebuilt from it, ``runs`` a resumed run's config.
Everything below this package takes typed values, not a ``DictConfig``."""

from omegaconf import OmegaConf

from semvpr.core.device import sweep_jobs

# hydra/launcher=side_by_side's n_jobs: how many jobs of a sweep run at once on the job's accelerator.
OmegaConf.register_new_resolver(
    "semvpr_sweep_jobs",
    lambda accelerator, devices, cpu_jobs, per_gpu=1: sweep_jobs(
        accelerator, devices, int(cpu_jobs), per_gpu=int(per_gpu)
    ),
    replace=True,
)
