"""Field components: the hash grid against a direct per-corner implementation, the spherical
harmonics basis, a field's output shape and scale, and the average of its weights."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch


def _naive_hashgrid(encoding, x):
    """The textbook definition: for each level and each of the 8 corners, hash (or index densely)
    the integer vertex, gather its features and weight them trilinearly (int64 arithmetic)."""
    cfg = encoding.config
    table = 1 << cfg.log2_hashmap_size
    out, offset = [], 0
    for level in range(cfg.n_levels):
        res = int(math.floor(cfg.base_resolution * cfg.per_level_scale ** level))
        pos = x.clamp(0, 1 - 1e-6) * res
        cell = pos.floor().long()
        frac = pos - cell
        acc = 0
        for corner in range(8):
            bits = torch.tensor([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1])
            v = cell + bits
            if (res + 1) ** 3 <= table:
                index, size = v[:, 0] + (res + 1) * (v[:, 1] + (res + 1) * v[:, 2]), (res + 1) ** 3
            else:
                index, size = (v[:, 0] ^ (v[:, 1] * 2654435761) ^ (v[:, 2] * 805459861)) & (table - 1), table
            weight = torch.where(bits.bool(), frac, 1 - frac).prod(-1)
            acc = acc + encoding.table[index + offset] * weight[:, None]
        out.append(acc)
        offset += size
    return torch.cat(out, -1)


@pytest.mark.parametrize("log2_size, base, scale, levels", [(15, 8, 1.6, 8), (10, 4, 2.0, 6), (12, 16, 1.3, 4)])
def test_hash_grid_matches_the_per_corner_definition(log2_size, base, scale, levels):
    from schemas.solver import HashGridConfig
    from services.solver.fields.encoding import HashGridEncoding

    torch.manual_seed(0)
    encoding = HashGridEncoding(HashGridConfig(log2_hashmap_size=log2_size, base_resolution=base,
                                               per_level_scale=scale, n_levels=levels))
    with torch.no_grad():
        encoding.table.normal_()
        x = torch.rand(5000, 3)
        assert torch.allclose(encoding(x), _naive_hashgrid(encoding, x), atol=1e-5)


def test_hash_grid_gradient_reaches_only_the_touched_rows():
    from schemas.solver import HashGridConfig
    from services.solver.fields.encoding import HashGridEncoding

    encoding = HashGridEncoding(HashGridConfig(n_levels=2, base_resolution=4, log2_hashmap_size=10))
    encoding(torch.full((1, 3), 0.3)).sum().backward()
    touched = (encoding.table.grad.abs().sum(1) > 0).sum().item()
    assert touched == 16  # 8 corners on each of 2 levels


def test_spherical_harmonics_are_orthonormal():
    from services.solver.fields.encoding import SphericalHarmonicsEncoding

    torch.manual_seed(1)
    d = torch.nn.functional.normalize(torch.randn(400_000, 3), dim=-1)
    y = SphericalHarmonicsEncoding(4)(d)                      # (N, 16)
    gram = (y.T @ y) * (4 * math.pi / d.shape[0])             # Monte Carlo ∫ Y_i Y_j dω
    assert torch.allclose(gram, torch.eye(16), atol=0.03)


def test_field_shapes_scale_and_normalisation():
    from schemas.solver import FieldConfig
    from services.solver.fields.field import NeuralField
    from services.solver.fields.query import FieldQuery

    field = NeuralField(FieldConfig(), channels=6, box_min=[0, 0, 0], box_max=[555, 548, 559])
    q = FieldQuery(torch.rand(10, 3) * 555, torch.nn.functional.normalize(torch.randn(10, 3), dim=-1),
                   torch.tensor([[0.0, 1.0, 0.0]]).repeat(10, 1))
    assert field(q).shape == (10, 6)
    x = field.normalize(torch.tensor([[0.0, 0, 0], [555, 548, 559]]))
    assert x.min() >= 0 and x.max() <= 1                      # any units map into the unit cube
    with torch.no_grad():
        field.output_scale.fill_(1000.0)
    assert field(q).abs().mean() > 10 * NeuralField(FieldConfig(), 6, [0, 0, 0], [555, 548, 559])(q).abs().mean()


def test_hash_grid_table_gradient_matches_autograd_of_the_definition():
    """The hand-written backward of the blend (one index_add_) against autograd through the
    per-corner definition."""
    from schemas.solver import HashGridConfig
    from services.solver.fields.encoding import HashGridEncoding

    torch.manual_seed(1)
    encoding = HashGridEncoding(HashGridConfig(log2_hashmap_size=10, base_resolution=4, per_level_scale=2.0,
                                               n_levels=6))
    with torch.no_grad():
        encoding.table.normal_()
    x, g = torch.rand(3000, 3), torch.randn(3000, encoding.output_dim)
    (encoding(x) * g).sum().backward()
    fast = encoding.table.grad.clone()
    encoding.table.grad = None
    (_naive_hashgrid(encoding, x) * g).sum().backward()
    assert torch.allclose(fast, encoding.table.grad, atol=1e-4)


def test_precomputed_inputs_survive_selection_and_give_the_same_values():
    """A query whose encoding inputs were precomputed (a pool's) evaluates like a fresh one, and
    a selection of it carries the precomputed rows along."""
    from schemas.solver import FieldConfig
    from services.solver.fields.field import NeuralField
    from services.solver.fields.query import FieldQuery

    torch.manual_seed(2)
    field = NeuralField(FieldConfig(), 4, [-1, -1, -1], [1, 1, 1])
    wo = torch.nn.functional.normalize(torch.randn(500, 3), dim=-1)
    fresh = FieldQuery(torch.rand(500, 3) * 2 - 1, wo, wo.flip(-1))
    pooled = field.precompute(FieldQuery(fresh.x, fresh.wo, fresh.n))
    index = torch.randperm(500)[:123]
    part = pooled.select(index)
    assert len(part.cache) == 2
    with torch.no_grad():
        assert torch.allclose(field(part), field(fresh.select(index)), atol=1e-6)
        assert torch.allclose(field(pooled), field(fresh), atol=1e-6)


def _small_field():
    from schemas.solver import FieldConfig, HashGridConfig, MLPConfig
    from services.solver.fields.field import NeuralField

    config = FieldConfig(encoding=HashGridConfig(n_levels=2, log2_hashmap_size=8),
                         mlp=MLPConfig(hidden_width=8, hidden_layers=1))
    return NeuralField(config, channels=2, box_min=[0, 0, 0], box_max=[1, 1, 1])


def _fill(field, value: float) -> None:
    with torch.no_grad():
        for p in field.parameters():
            p.fill_(value)


def test_weight_average_follows_its_update_rule_and_restarts_when_the_parameters_change():
    """w̄_k = β_k w̄_(k-1) + (1 - β_k) w_k with β_k = min(β, (1 + k) / (10 + k)), k counting the
    updates since the scene's parameters last changed; buffers are copied, not averaged."""
    from services.solver.fields.averaging import WeightAverage

    field = _small_field()
    _fill(field, 0.0)
    average = WeightAverage(field, decay=0.5)
    expected, values = 0.0, np.array([0.3])
    for k, w in enumerate([1.0, 2.0, 4.0, 8.0]):
        _fill(field, w)
        average.update(values)
        beta = min(0.5, (1 + k) / (10 + k))
        expected = beta * expected + (1 - beta) * w
        assert all(torch.allclose(p, torch.full_like(p, expected)) for p in average.average.parameters())
    assert expected != pytest.approx(8.0)                       # it did average
    with torch.no_grad():
        field.output_scale.fill_(7.0)
    _fill(field, 16.0)
    average.update(np.array([0.31]))                            # a parameter step: k = 0 again
    restarted = 0.1 * expected + 0.9 * 16.0
    assert all(torch.allclose(p, torch.full_like(p, restarted)) for p in average.average.parameters())
    assert torch.equal(average.average.output_scale, field.output_scale)
    assert not any(p.requires_grad for p in average.average.parameters())


def test_weight_average_survives_its_state_dict_and_rejects_a_decay_outside_zero_one():
    from services.solver.fields.averaging import WeightAverage

    field = _small_field()
    average = WeightAverage(field, decay=0.9)
    for w in (1.0, 3.0):
        _fill(field, w)
        average.update(np.array([0.5, 0.5]))
    state = average.state_dict()
    restored = WeightAverage(_small_field(), decay=0.9)
    restored.load_state_dict(state)
    _fill(field, 5.0)
    _fill(restored.field, 5.0)
    average.update(np.array([0.5, 0.5]))
    restored.update(np.array([0.5, 0.5]))                       # same count, same parameters: no restart
    assert all(torch.equal(a, b) for a, b in zip(average.average.parameters(), restored.average.parameters()))
    for decay in (-0.1, 1.0):
        with pytest.raises(ValueError, match=r"\[0, 1\)"):
            WeightAverage(field, decay)
