"""The bounded sub-model cache (ours) with a fake loader: no nerfstudio run is built."""

from __future__ import annotations

import gc
import weakref

import pytest
import torch
from torch import nn

from nerfuser_ns.adapters import ModelCache, NerfactoAdapter


class FakeNerf(nn.Module):
    """Just enough of a nerfacto model for :class:`NerfactoAdapter`."""

    def __init__(self, i: int) -> None:
        super().__init__()
        self.i = i
        self.field = nn.Linear(2, 2)
        self.proposal_sampler = self.density_fns = self.renderer_rgb = None
        self.cycle = [self]  # a reference cycle, as real models have: eviction must still free it


def cache_of(limit: int, count: int = 4):
    loaded: list[int] = []
    alive: dict[int, list[weakref.ref]] = {}

    def loader(i: int) -> FakeNerf:
        loaded.append(i)
        m = FakeNerf(i)
        alive.setdefault(i, []).append(weakref.ref(m))
        return m

    return ModelCache(count, loader, limit, names=[f"n{i}" for i in range(count)]), loaded, alive


def test_least_recently_used_is_evicted_and_the_limit_holds(capsys):
    cache, loaded, alive = cache_of(limit=2)
    for i in (0, 1, 0, 2, 3, 0, 0, 1):
        adapter = cache.get(i)
        assert isinstance(adapter, NerfactoAdapter) and adapter.model.i == i
        assert len(cache.resident()) <= 2
        assert cache.resident()[-1] == i  # the one just used is the most recent
    del adapter
    # 0 1 | 0 (hit) | 2 evicts 1 | 3 evicts 0 | 0 reloaded, evicts 2 | 0 (hit) | 1 reloaded, evicts 3
    assert loaded == [0, 1, 2, 3, 0, 1]
    assert cache.resident() == [0, 1]
    assert (cache.loads, cache.evictions) == (6, 4)
    # The evicted models are freed at once (their weights released), the resident ones are not.
    gc.disable()
    try:
        dead = {i: [r() is None for r in refs] for i, refs in alive.items()}
    finally:
        gc.enable()
    assert dead == {0: [True, False], 1: [True, False], 2: [True], 3: [True]}
    out = capsys.readouterr().out
    assert out.count("evicting the least recently used") == 1  # one line, the first time only
    assert "'n1'" in out and "max_resident_nerfs" in out


def test_models_stay_frozen_out_of_the_state_dict_and_move_with_the_cache():
    cache, _, _ = cache_of(limit=3)
    model = cache.get(1).model
    assert not model.training and not any(p.requires_grad for p in model.parameters())
    cache.train()
    assert not model.training
    assert list(cache.state_dict()) == [] and list(cache.parameters()) == []
    cache.to(torch.float64)
    assert model.field.weight.dtype == torch.float64
    assert len(cache) == 4 and cache.resident() == [1]


@pytest.mark.parametrize("limit", [0, -1, 1.5, True])
def test_a_limit_below_one_is_refused_in_one_line(limit):
    with pytest.raises(ValueError, match=r"max_resident_nerfs must be a whole number >= 1") as e:
        ModelCache(3, FakeNerf, limit)
    assert "\n" not in str(e.value)


def test_a_model_without_an_adapter_is_named_and_an_unknown_index_refused():
    cache = ModelCache(2, lambda i: nn.Linear(1, 1), 1, names=["a", "b"])
    with pytest.raises(TypeError, match="run 'b'"):
        cache.get(1)
    with pytest.raises(IndexError):
        cache.get(2)
    assert cache.loads == 0 and cache.resident() == []
