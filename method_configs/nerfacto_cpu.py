"""``nerfacto-cpu``: stock nerfacto, sized to train in minutes on a CPU (small hash grid, fewer samples).

It is still nerfacto (same model class, fields and losses): runs trained with it load anywhere nerfacto loads.
Differences from ``nerfacto``: torch hash grid (no tcnn), 2^15-entry tables over 12 levels, 32-wide MLPs,
(64, 32) proposal + 32 NeRF samples per ray, no camera-pose optimisation (use it with exact poses, e.g. the
generated ground-truth scenes), a single-process datamanager, CPU device, no mixed precision, and rare
evaluations. Every field can still be changed on the command line as usual.
"""

from __future__ import annotations

from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.configs.base_config import MachineConfig, ViewerConfig
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManagerConfig
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.models.nerfacto import NerfactoModelConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig
from nerfstudio.plugins.types import MethodSpecification


def nerfacto_cpu_config(max_num_iterations: int = 3000) -> TrainerConfig:
    """The nerfacto-cpu trainer config (a function so tests and scripts can derive variants)."""
    return TrainerConfig(
        method_name="nerfacto-cpu",
        steps_per_eval_batch=1_000_000,
        steps_per_eval_image=1_000_000,
        steps_per_eval_all_images=1_000_000,
        steps_per_save=1000,
        save_only_latest_checkpoint=True,
        max_num_iterations=max_num_iterations,
        mixed_precision=False,
        machine=MachineConfig(device_type="cpu", num_devices=1),
        pipeline=VanillaPipelineConfig(
            datamanager=VanillaDataManagerConfig(
                dataparser=NerfstudioDataParserConfig(),
                train_num_rays_per_batch=1024,
                eval_num_rays_per_batch=1024,
            ),
            model=NerfactoModelConfig(
                implementation="torch",
                eval_num_rays_per_chunk=1 << 13,
                average_init_density=0.01,
                log2_hashmap_size=15,
                num_levels=12,
                max_res=1024,
                hidden_dim=32,
                hidden_dim_color=32,
                num_proposal_samples_per_ray=(64, 32),
                num_nerf_samples_per_ray=32,
                proposal_warmup=1000,
                proposal_net_args_list=[
                    {"hidden_dim": 16, "log2_hashmap_size": 14, "num_levels": 5, "max_res": 128, "use_linear": False},
                    {"hidden_dim": 16, "log2_hashmap_size": 14, "num_levels": 5, "max_res": 256, "use_linear": False},
                ],
                camera_optimizer=CameraOptimizerConfig(mode="off"),
            ),
        ),
        optimizers={
            "proposal_networks": {
                "optimizer": AdamOptimizerConfig(lr=1e-2, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=max_num_iterations),
            },
            "fields": {
                "optimizer": AdamOptimizerConfig(lr=1e-2, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=max_num_iterations),
            },
            "camera_opt": {
                "optimizer": AdamOptimizerConfig(lr=1e-3, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=5000),
            },
        },
        viewer=ViewerConfig(num_rays_per_chunk=1 << 13),
        vis="tensorboard",
    )


nerfacto_cpu_method = MethodSpecification(
    config=nerfacto_cpu_config(),
    description="nerfacto sized for CPU training in minutes (small hash grid, fewer samples; nerfuser_ns preset).",
)
