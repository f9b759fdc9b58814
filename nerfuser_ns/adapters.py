"""Sub-models inside a fused model: the adapters that query a nerfstudio model's ray samples (nerfacto's proposal
sampler and field; append to :data:`ADAPTERS` for another family), the holder that keeps the frozen sub-models out
of the fused checkpoint, and (ours) the bounded cache that loads them on first use."""

from __future__ import annotations

import gc
import weakref
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from jaxtyping import Float, Int
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.models.base_model import Model
from nerfstudio.utils import colors
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor, nn

# ----------------------------------------------------------------------------------------------------------------------
# Sub-model adapters


@dataclass
class NerfSamples:
    """One NeRF's samples along a batch of rays, in ITS OWN frame's ray distances."""

    starts: Float[Tensor, "num_rays num_samples"]
    ends: Float[Tensor, "num_rays num_samples"]
    weights: Float[Tensor, "num_rays num_samples"]
    """Termination probabilities ``T_k alpha_k``."""
    rgbs: Float[Tensor, "num_rays num_samples 3"]
    background_rgb: Float[Tensor, "num_rays 3"]
    """The colour its own renderer puts behind the samples (nerfacto "last_sample": the last sample's colour)."""


@dataclass
class QueriedSamples:
    """One NeRF's samples for some or all rays of a batch, as the fused model queried them."""

    samples: NerfSamples
    """The samples, one row per queried ray."""
    scale: Float[Tensor, "num_queried 1"]
    """``k`` with ``t_nerf = k * t_common``, per queried ray."""
    rows: Int[Tensor, " num_queried"] | None = None
    """The batch rays queried, in order; None: all of them."""


class NerfAdapter:
    """The small interface the fused model needs from a sub-model (subclass it for other ray-marching models).

    ``samples`` gets rays in the sub-model's own frame, nears/fars already set, and returns its samples.
    """

    def __init__(self, model: Model) -> None:
        self.model = model

    @classmethod
    def supports(cls, model: Model) -> bool:
        raise NotImplementedError

    @classmethod
    def supports_class(cls, model_class: type) -> bool | None:
        """Whether models of ``model_class`` (a run config's ``pipeline.model._target``) can be adapted, judged
        before any is built; None when only a built model tells (:meth:`supports`)."""
        return None

    def collide(self, ray_bundle: RayBundle) -> RayBundle:
        """Sets nears/fars as the sub-model would (its own collider, in its frame) unless already set."""
        collider = getattr(self.model, "collider", None)
        if collider is not None:
            ray_bundle = collider(ray_bundle)
        return ray_bundle

    def samples(self, ray_bundle: RayBundle) -> NerfSamples:
        raise NotImplementedError


def _background(background_color: Any, rgbs: Tensor) -> Tensor:
    """The background colour a nerfstudio RGBRenderer would use in eval, per ray."""
    if background_color == "last_sample":
        return rgbs[..., -1, :]
    if background_color == "random" or background_color is None:
        return torch.zeros_like(rgbs[..., -1, :])  # eval renders "random" as if on black
    if isinstance(background_color, str):
        background_color = colors.COLORS_DICT[background_color]
    return torch.as_tensor(background_color, dtype=rgbs.dtype, device=rgbs.device).expand_as(rgbs[..., -1, :])


class NerfactoAdapter(NerfAdapter):
    """nerfacto and its family: ``proposal_sampler`` -> ``field.forward`` -> ``ray_samples.get_weights``."""

    @classmethod
    def supports(cls, model: Model) -> bool:
        return all(hasattr(model, a) for a in ("proposal_sampler", "density_fns", "field", "renderer_rgb"))

    @classmethod
    def supports_class(cls, model_class: type) -> bool | None:
        # by name: importing nerfstudio.models.nerfacto here would print its fields' deprecation warnings at the start
        # of every command, before a one-line error
        return any(f"{c.__module__}.{c.__qualname__}" == "nerfstudio.models.nerfacto.NerfactoModel"
                   for c in model_class.__mro__)  # fmt: skip

    def samples(self, ray_bundle: RayBundle) -> NerfSamples:
        m = self.model
        ray_samples, _, _ = m.proposal_sampler(ray_bundle, density_fns=m.density_fns)
        field_outputs = m.field.forward(ray_samples, compute_normals=False)
        weights = ray_samples.get_weights(field_outputs[FieldHeadNames.DENSITY])
        rgbs = torch.nan_to_num(field_outputs[FieldHeadNames.RGB])  # as RGBRenderer does in eval
        return NerfSamples(
            starts=ray_samples.frustums.starts[..., 0],
            ends=ray_samples.frustums.ends[..., 0],
            weights=weights[..., 0],
            rgbs=rgbs,
            background_rgb=_background(m.renderer_rgb.background_color, rgbs),
        )


ADAPTERS: list[type[NerfAdapter]] = [NerfactoAdapter]
"""Adapter classes tried in order; append yours to support another model family."""


class UnsupportedRunError(TypeError):
    """A run whose model no adapter can query for ray samples (its message names the run)."""


def check_model_class(name: str, model_class: type, method: str) -> None:
    """:class:`UnsupportedRunError` naming run ``name`` when every adapter rejects its model class (``ns-train
    nerfuser`` asks before it writes anything: e.g. a splatfacto or instant-ngp run beside nerfacto ones; such runs
    still register)."""
    if all(cls.supports_class(model_class) is False for cls in ADAPTERS):
        raise UnsupportedRunError(
            f"run {name!r} was trained with {method} ({model_class.__name__}), whose ray samples cannot be merged "
            "with the others': fuse nerfacto-family runs (nerfacto, nerfacto-big, depth-nerfacto ...), or register a "
            "NerfAdapter subclass in nerfuser_ns.adapters.ADAPTERS"
        )


def make_adapter(model: Model, name: str | None = None) -> NerfAdapter:
    """The first adapter of :data:`ADAPTERS` that supports ``model``; :class:`UnsupportedRunError` otherwise, naming
    run ``name`` when given (with several runs the model class alone does not say which)."""
    for cls in ADAPTERS:
        if cls.supports(model):
            return cls(model)
    message = (f"nerfuser: no adapter for {type(model).__name__}; supported: nerfacto-family models "
               "(register a NerfAdapter subclass in nerfuser_ns.adapters.ADAPTERS)")  # fmt: skip
    if name is not None:
        message = f"run {name!r}: {message}; its ray samples cannot be merged with the others'"
    raise UnsupportedRunError(message)


class FrozenModels(nn.Module):
    """Holds the sub-models outside ``parameters()`` and ``state_dict()`` but moves them with ``.to()``.

    They are rebuilt from their own runs at load time, so the fused checkpoint does not copy their weights, and the
    optimizer sees no parameters. They always stay in eval mode.
    """

    def __init__(self, models: Sequence[Model]) -> None:
        super().__init__()
        self.models: list[Model] = list(models)  # a plain list: not registered as children
        for m in self.models:
            m.eval()
            m.requires_grad_(False)

    def _apply(self, fn, recurse: bool = True):  # noqa: ANN001 - torch's signature
        seen: set[int] = set()
        for m in self.models:
            if id(m) not in seen:  # the same model may appear twice (tests fuse copies)
                seen.add(id(m))
                m._apply(fn)
        return super()._apply(fn, recurse)

    def train(self, mode: bool = True):
        super().train(mode)
        for m in self.models:
            m.eval()
        return self

    def __len__(self) -> int:
        return len(self.models)


class ModelCache(nn.Module):
    """Sub-models loaded on first use and kept in a least-recently-used cache of at most ``limit`` (ours).

    ``loader(i)`` builds sub-model ``i`` (the fused model passes one that rebuilds the run on its current device).
    :meth:`get` returns its adapter, loading it if needed; before a load, the least recently used models are dropped
    so that no more than ``limit`` are ever resident, and their memory is released. Like :class:`FrozenModels`, the
    models stay out of ``parameters()`` and ``state_dict()``, in eval mode, and move with ``.to()``.
    ``loads`` and ``evictions`` count what happened; the first eviction logs one line.
    """

    def __init__(
        self, count: int, loader: Callable[[int], Model], limit: int, names: Sequence[str] | None = None
    ) -> None:
        super().__init__()
        if isinstance(limit, bool) or not isinstance(limit, int) or limit < 1:
            raise ValueError(f"nerfuser: max_resident_nerfs must be a whole number >= 1 (or None: all), got {limit!r}")
        self.count, self.loader, self.limit = count, loader, limit
        self.names = [str(n) for n in names] if names is not None else [str(i) for i in range(count)]
        self._resident: OrderedDict[int, NerfAdapter] = OrderedDict()  # least recently used first
        self.loads = 0
        self.evictions = 0

    def get(self, i: int) -> NerfAdapter:
        """Sub-model ``i``'s adapter, now the most recently used; loaded (after any eviction) if not resident."""
        if not 0 <= i < self.count:
            raise IndexError(f"nerfuser: no sub-model {i} (of {self.count})")
        if i in self._resident:
            self._resident.move_to_end(i)
            return self._resident[i]
        while len(self._resident) >= self.limit:  # evict first: never more than `limit` in memory, even mid-load
            self._evict()
        model = self.loader(i)
        model.eval()
        model.requires_grad_(False)
        adapter = make_adapter(model, self.names[i])
        self._resident[i] = adapter
        self.loads += 1
        return adapter

    def resident(self) -> list[int]:
        """The resident sub-models, least recently used first."""
        return list(self._resident)

    def _evict(self) -> None:
        i, adapter = self._resident.popitem(last=False)
        on_cuda = any(p.is_cuda for p in adapter.model.parameters())
        model = weakref.ref(adapter.model)
        del adapter
        self.evictions += 1
        if self.evictions == 1:
            CONSOLE.print(f"nerfuser: more than {self.limit} sub-models needed: evicting the least recently used "
                          f"({self.names[i]!r}); evicted ones are reloaded from their runs when needed again "
                          "(slower; raise max_resident_nerfs if memory allows)")  # fmt: skip
        if model() is not None:  # held by reference cycles: free the weights now, not at some later collection
            gc.collect()
        if on_cuda:
            torch.cuda.empty_cache()

    def _apply(self, fn, recurse: bool = True):  # noqa: ANN001 - torch's signature
        for adapter in self._resident.values():
            adapter.model._apply(fn)
        return super()._apply(fn, recurse)

    def train(self, mode: bool = True):
        super().train(mode)
        for adapter in self._resident.values():
            adapter.model.eval()
        return self

    def __len__(self) -> int:
        return self.count
