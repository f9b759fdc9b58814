"""``nerfuser``: the fused method (several frozen, registered NeRFs rendered as one blended scene).

Placeholder until the fused-method issue lands: the method is registered so that ``ns-train --help`` lists it,
and training it says clearly that it is not implemented yet.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from nerfstudio.configs.base_config import MachineConfig
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig
from nerfstudio.plugins.types import MethodSpecification


@dataclass
class _NotImplementedPipelineConfig(VanillaPipelineConfig):
    _target: type = field(default_factory=lambda: _not_implemented)


def _not_implemented(*args, **kwargs):
    raise SystemExit("nerfuser: the fused method is not implemented yet (see the project's issue tracker)")


nerfuser_method = MethodSpecification(
    config=TrainerConfig(
        method_name="nerfuser",
        machine=MachineConfig(device_type="cpu"),
        pipeline=_NotImplementedPipelineConfig(),
        vis="tensorboard",
    ),
    description="NeRFuser: blend several registered nerfstudio runs (IDW-Sample). [not implemented yet]",
)
