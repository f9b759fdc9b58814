"""``nerfuser``: the fused method (several frozen, registered NeRFs rendered as one blended scene).

``ns-train nerfuser --data <fusion spec>`` builds nothing new: it loads the runs named by the spec (see
``nerfuser_ns.data``), rebuilt from their own config.yml and checkpoints, and writes a normal run folder
(config.yml, dataparser_transforms.json, a checkpoint without the sub-models' weights) after zero iterations.
``ns-render``, ``ns-eval`` and ``ns-viewer`` then load that run like any other; the blend method (``auto`` by
default: IDW-Sample around objects, IDW-2D from a camera rig, coverage along a path), gamma and tau are
``--pipeline.model.blend-method/gamma/tau`` at train time, and can be changed at render time (viewer controls, or
the environment variables NERFUSER_BLEND_METHOD / NERFUSER_GAMMA / NERFUSER_TAU).
"""

from __future__ import annotations

import torch
from nerfstudio.configs.base_config import LocalWriterConfig, LoggingConfig, MachineConfig, ViewerConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig
from nerfstudio.plugins.types import MethodSpecification

from nerfuser_ns.data import NerfuserDataManagerConfig, NerfuserTrainerConfig
from nerfuser_ns.model import NerfuserModelConfig


def nerfuser_config() -> NerfuserTrainerConfig:
    """The nerfuser trainer config (a function so tests and scripts can derive variants)."""
    return NerfuserTrainerConfig(
        method_name="nerfuser",
        max_num_iterations=0,  # nothing to train: the run is written as soon as the sub-models load
        steps_per_eval_batch=1_000_000,
        steps_per_eval_image=1_000_000,
        steps_per_eval_all_images=1_000_000,
        steps_per_save=1_000_000,
        save_only_latest_checkpoint=True,
        mixed_precision=False,
        machine=MachineConfig(device_type="cuda" if torch.cuda.is_available() else "cpu", num_devices=1),
        pipeline=VanillaPipelineConfig(
            datamanager=NerfuserDataManagerConfig(),
            model=NerfuserModelConfig(),
        ),
        optimizers={},
        # No iterations means no step statistics: nerfstudio's local (terminal) writer would fail printing them.
        logging=LoggingConfig(local_writer=LocalWriterConfig(enable=False)),
        viewer=ViewerConfig(num_rays_per_chunk=1 << 12),
        vis="tensorboard",
    )


nerfuser_method = MethodSpecification(
    config=nerfuser_config(),
    description="NeRFuser: blend several registered nerfstudio runs (IDW-Sample and baselines); sub-models frozen.",
)
