"""The render-time blend settings of the fused model: one frozen, validated value (:class:`BlendSettings`).

Every writer builds a new value through it: the model config, the ``NERFUSER_BLEND_METHOD`` / ``NERFUSER_GAMMA`` /
``NERFUSER_TAU`` / ``NERFUSER_APPEARANCE_MATCHING`` environment (sweeps, ``ns-eval``, ``ns-render``), the viewer's
controls. The maths that uses it is
:mod:`nerfuser_ns.blending`.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from typing import Any

import torch

from nerfuser_ns.blend_choice import AUTO, BLEND_CHOICES
from nerfuser_ns.blending import PAPER_OBJECT_CENTRIC
from nerfuser_ns.coverage import CoverageParams
from nerfuser_ns.runtime import OFF_WORDS, ON_WORDS

ENV_METHOD = "NERFUSER_BLEND_METHOD"
ENV_GAMMA = "NERFUSER_GAMMA"
ENV_TAU = "NERFUSER_TAU"
ENV_APPEARANCE = "NERFUSER_APPEARANCE_MATCHING"

SHARE_PALETTE = torch.tensor(
    [
        [0.122, 0.467, 0.706],
        [1.000, 0.498, 0.055],
        [0.173, 0.627, 0.173],
        [0.839, 0.153, 0.157],
        [0.580, 0.404, 0.741],
        [0.549, 0.337, 0.294],
        [0.890, 0.467, 0.761],
        [0.498, 0.498, 0.498],
        [0.737, 0.741, 0.133],
        [0.090, 0.745, 0.812],
    ]
)
"""Colours of the colour-coded share map (tab10): NeRF i gets ``SHARE_PALETTE[i % 10]``."""


@dataclass(frozen=True)
class BlendSettings:
    """The render-time blend settings: one frozen value, checked when it is made (:meth:`checked`).

    Every writer (the model config, the ``NERFUSER_*`` environment, the viewer, sweeps) builds a new value through
    :meth:`from_config` or :meth:`replace`; nothing validates per forward pass.
    """

    method: str = AUTO
    """A blend method, or ``auto`` (ours): the fused model resolves it once from the training cameras
    (:mod:`nerfuser_ns.blend_choice`)."""
    gamma: float = PAPER_OBJECT_CENTRIC[0]
    tau: float | None = PAPER_OBJECT_CENTRIC[1]
    """None (or 0 where given): the distance test is off."""
    reference_nerf: int = 0
    coverage: CoverageParams = CoverageParams()
    """Constants of the ``coverage`` method."""
    appearance_matching: bool = True
    """Map each NeRF's colours with its colour map from the registration file (ours)."""

    @classmethod
    def from_config(cls, config: Any, environ: Any = None) -> BlendSettings:
        """A model config's ``blend_method`` / ``gamma`` / ``tau`` / ``reference_nerf`` / ``appearance_matching``,
        overridden by ``NERFUSER_BLEND_METHOD`` / ``_GAMMA`` / ``_TAU`` / ``_APPEARANCE_MATCHING``; ValueError (one
        line, naming the option or variable) when a value is unusable."""
        environ = os.environ if environ is None else environ

        def number(name: str, value: Any) -> float:
            try:
                return float(value)
            except (TypeError, ValueError):
                raise ValueError(f"nerfuser: {name} must be a number, got {value!r}") from None

        method = environ.get(ENV_METHOD, config.blend_method)
        gamma = number(ENV_GAMMA, environ[ENV_GAMMA]) if ENV_GAMMA in environ else number("gamma", config.gamma)
        tau: Any = config.tau
        if ENV_TAU in environ:
            raw = environ[ENV_TAU].strip()
            tau = None if raw.lower() in ("", "none", "off") else number(ENV_TAU, raw)
        elif tau is not None:
            tau = number("tau", tau)
        coverage = getattr(config, "coverage", None) or CoverageParams()
        matching = bool(getattr(config, "appearance_matching", True))
        if ENV_APPEARANCE in environ:
            raw = environ[ENV_APPEARANCE].strip().lower()
            if raw not in ON_WORDS + OFF_WORDS:
                raise ValueError(f"nerfuser: {ENV_APPEARANCE} must be one of {ON_WORDS + OFF_WORDS}, got {raw!r}")
            matching = raw in ON_WORDS
        return cls(str(method), gamma, tau, int(config.reference_nerf), coverage, matching).checked()

    def checked(self, num_nerfs: int | None = None) -> BlendSettings:
        """This value with ``tau = 0`` read as off, or ValueError (one line) naming what is wrong."""
        if self.method not in BLEND_CHOICES:
            raise ValueError(f"nerfuser: unknown blend method {self.method!r}; choose one of {BLEND_CHOICES}")
        if not (self.gamma >= 0):  # also rejects NaN
            raise ValueError(f"nerfuser: gamma must be >= 0, got {self.gamma}")
        if self.tau is not None and self.tau != 0 and not (self.tau >= 1):
            raise ValueError(f"nerfuser: tau must be >= 1 (a distance ratio), or 0 / None to turn the test off; "
                             f"got {self.tau}")  # fmt: skip
        if num_nerfs is not None and not -num_nerfs <= self.reference_nerf < num_nerfs:
            raise ValueError(f"nerfuser: reference_nerf {self.reference_nerf} out of range for {num_nerfs} NeRFs")
        if not isinstance(self.appearance_matching, bool):
            raise ValueError(f"nerfuser: appearance_matching must be True or False, got {self.appearance_matching!r}")
        self.coverage.checked()
        return self if self.tau != 0 else dataclasses.replace(self, tau=None)

    def replace(self, num_nerfs: int | None = None, **changes: Any) -> BlendSettings:
        """A checked copy with ``changes`` (the only way settings change after the model is built)."""
        return dataclasses.replace(self, **changes).checked(num_nerfs)
