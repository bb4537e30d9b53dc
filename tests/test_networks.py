"""History encoders (alignrl/agents/networks.py): shapes, gradients, exact indifference to
padding, GTrXL gating at initialisation, determinism, the registry."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from alignrl.agents.networks import (
    ENCODERS,
    GTrXLEncoder,
    HistoryEncoder,
    make_encoder,
)

HISTORY, FEATURES = 8, 7  # the defocus task: 8 rows of 5 + 2 * 1 knob columns

# Each case: (registry name, options). The deeper variant of GTrXL exercises the code path
# that the defaults skip (all-row queries in early blocks).
CASES = {
    "mlp": ("mlp", {}),
    "gru": ("gru", {}),
    "gtrxl": ("gtrxl", {}),
    "gtrxl-2-layers": ("gtrxl", {"layers": 2}),
}


def histories(valid_counts: list[int], seed: int = 0, padding: str = "zeros") -> Tensor:
    """Right-aligned histories like alignrl/envs/core.py: the last `valid` rows of each are
    real steps (column 0 = 1); the rows in front are padding, filled with zeros or, to prove
    they are ignored, with garbage (any values, column 0 = 0)."""
    generator = torch.Generator().manual_seed(seed)
    batch = torch.rand(len(valid_counts), HISTORY, FEATURES, generator=generator) * 2 - 1
    batch[..., 0] = 1.0
    for index, valid in enumerate(valid_counts):
        pad = HISTORY - valid
        if padding == "zeros":
            batch[index, :pad] = 0.0
        else:
            batch[index, :pad] = 5.0 * torch.randn(pad, FEATURES, generator=generator)
            batch[index, :pad, 0] = 0.0
    return batch


def build(case: str, seed: int = 0) -> HistoryEncoder:
    name, options = CASES[case]
    torch.manual_seed(seed)
    return make_encoder(name, HISTORY, FEATURES, **options)


@pytest.mark.parametrize("batch", [1, 32])
@pytest.mark.parametrize("case", list(CASES))
def test_output_shape(case: str, batch: int) -> None:
    encoder = build(case)
    encoded, second = encoder(histories([HISTORY] * batch))
    assert encoded.shape == (batch, encoder.output_dim)
    assert encoded.dtype == torch.float32 and torch.isfinite(encoded).all()
    assert second is None


@pytest.mark.parametrize("case", list(CASES))
def test_gradients_reach_every_parameter(case: str) -> None:
    encoder = build(case)
    encoded, _ = encoder(histories([HISTORY, 5, 1, 3] * 4))
    encoded.square().sum().backward()
    for name, parameter in encoder.named_parameters():
        assert parameter.grad is not None, f"{name} got no gradient"
        assert torch.isfinite(parameter.grad).all(), f"{name} has a non-finite gradient"
        assert parameter.grad.abs().sum() > 0, f"{name} has an all-zero gradient"


@pytest.mark.parametrize("case", ["gru", "gtrxl", "gtrxl-2-layers"])
def test_padding_is_ignored(case: str) -> None:
    """A padded history gives the output of its valid rows alone, whatever the padding holds:
    take full histories, replace their oldest rows by padding, and compare each with the
    encoder run on just its valid suffix."""
    encoder = build(case)
    valid_counts = [8, 7, 5, 3, 2, 1]
    with torch.no_grad():
        for padding in ("zeros", "garbage"):
            padded = histories(valid_counts, padding=padding)
            encoded, _ = encoder(padded)
            for index, valid in enumerate(valid_counts):
                suffix = padded[index : index + 1, HISTORY - valid :]  # (1, valid, F)
                alone, _ = encoder(suffix)
                torch.testing.assert_close(encoded[index : index + 1], alone, atol=1e-5, rtol=0)
        # Not vacuous: the outputs do depend on which rows are valid.
        full, _ = encoder(histories([HISTORY] * len(valid_counts)))
        assert (full[1:] - encoded[1:]).abs().amax(dim=1).min() > 1e-3


def _block_change(gate_bias: float) -> float:
    """Relative change ||block(x) - x|| / ||x|| of the embedding through the first block."""
    torch.manual_seed(0)  # the same weights for every gate_bias: only b_g differs
    encoder = GTrXLEncoder(HISTORY, FEATURES, gate_bias=gate_bias)
    with torch.no_grad():
        stream, key_valid = encoder.embed(histories([8, 6, 4, 2] * 8))
        out = encoder.blocks[0](stream, key_valid)
    return float((out - stream).norm() / stream.norm())


def test_gtrxl_blocks_start_near_identity() -> None:
    """Parisotto et al. 2019: with the update-gate bias b_g > 0 a gated block starts close to
    the identity map; without it, the block rewrites its input far more."""
    near_identity = _block_change(2.0)
    ungated = _block_change(0.0)
    assert near_identity < 0.5
    assert ungated > 2.0 * near_identity
    assert _block_change(4.0) < near_identity


@pytest.mark.parametrize("case", list(CASES))
def test_same_seed_same_parameters_and_outputs(case: str) -> None:
    first, second = build(case, seed=7), build(case, seed=7)
    for (name, a), (_, b) in zip(first.named_parameters(), second.named_parameters(), strict=True):
        assert torch.equal(a, b), name
    batch = histories([8, 4, 1])
    with torch.no_grad():
        assert torch.equal(first(batch)[0], second(batch)[0])
    other = build(case, seed=8)
    assert not all(
        torch.equal(a, b) for a, b in zip(first.parameters(), other.parameters(), strict=True)
    )


def test_make_encoder_names_what_is_wrong() -> None:
    with pytest.raises(ValueError, match=r"'transformer'.*gru, gtrxl, mlp"):
        make_encoder("transformer", HISTORY, FEATURES)
    with pytest.raises(ValueError, match=r"'gtrxl' has no option 'dmodel'.*d_model"):
        make_encoder("gtrxl", HISTORY, FEATURES, dmodel=16)
    with pytest.raises(ValueError, match=r"'mlp' has no option 'heads'.*hidden"):
        make_encoder("mlp", HISTORY, FEATURES, heads=2)
    with pytest.raises(ValueError, match="divisible by heads"):
        make_encoder("gtrxl", HISTORY, FEATURES, d_model=30, heads=4)
    assert isinstance(make_encoder("gru", HISTORY, FEATURES, hidden=16), ENCODERS["gru"])


def test_forward_rejects_wrong_input() -> None:
    mlp = build("mlp")
    with pytest.raises(ValueError, match=r"\(batch, rows, 7\)"):
        mlp(torch.zeros(HISTORY, FEATURES))
    with pytest.raises(ValueError, match="exactly 8 rows"):
        mlp(torch.zeros(2, 5, FEATURES))


def test_all_padding_history_stays_finite() -> None:
    """A zero observation (no valid row at all) must not make the attention softmax NaN."""
    for case in ("gtrxl", "gtrxl-2-layers", "gru"):
        encoded, _ = build(case)(torch.zeros(2, HISTORY, FEATURES))
        assert torch.isfinite(encoded).all(), case


@pytest.mark.parametrize("case", list(CASES))
def test_forward_on_cuda_matches_cpu(case: str) -> None:
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    encoder = build(case)
    batch = histories([8, 5, 1, 3] * 8, padding="garbage")
    expected, _ = encoder(batch)
    encoder.to("cuda")
    encoded, _ = encoder(batch.cuda())
    encoded.square().sum().backward()
    assert encoded.device.type == "cuda"
    torch.testing.assert_close(encoded.cpu(), expected, atol=1e-4, rtol=1e-4)
    assert all(p.grad is not None and p.grad.is_cuda for p in encoder.parameters())
