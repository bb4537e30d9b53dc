"""History encoders (alignrl/agents/networks.py): shapes, gradients, exact indifference to
padding, GTrXL gating at initialisation and its memory, determinism, the registry."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from alignrl.agents.networks import (
    ENCODERS,
    GTrXLEncoder,
    HistoryEncoder,
    Memory,
    make_encoder,
)

HISTORY, FEATURES = 8, 7  # the defocus task: 8 rows of 5 + 2 * 1 knob columns

# Each case: (registry name, options). The deeper and memory variants of GTrXL exercise the
# code paths that the defaults skip (all-row queries in early blocks, attention over memory).
CASES = {
    "mlp": ("mlp", {}),
    "gru": ("gru", {}),
    "gtrxl": ("gtrxl", {}),
    "gtrxl-2-layers": ("gtrxl", {"layers": 2}),
    "gtrxl-memory": ("gtrxl", {"layers": 2, "memory_length": 4}),
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


def full_memory(encoder: HistoryEncoder, batch: int, seed: int = 1) -> Memory:
    """A memory whose every slot holds a (random) real step."""
    generator = torch.Generator().manual_seed(seed)
    memory = encoder.initial_memory(batch)
    assert memory is not None
    layers = [torch.randn(layer.shape, generator=generator) for layer in memory.layers]
    return Memory(layers, torch.ones_like(memory.valid))


@pytest.mark.parametrize("batch", [1, 32])
@pytest.mark.parametrize("case", list(CASES))
def test_output_shape(case: str, batch: int) -> None:
    encoder = build(case)
    encoded, memory = encoder(histories([HISTORY] * batch))
    assert encoded.shape == (batch, encoder.output_dim)
    assert encoded.dtype == torch.float32 and torch.isfinite(encoded).all()
    if getattr(encoder, "memory_length", 0):
        assert memory is not None and memory.batch_size == batch
    else:
        assert memory is None


@pytest.mark.parametrize("case", list(CASES))
def test_gradients_reach_every_parameter(case: str) -> None:
    encoder = build(case)
    memory = full_memory(encoder, 16) if encoder.keeps_memory else None
    encoded, _ = encoder(histories([HISTORY, 5, 1, 3] * 4), memory)
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
        stream, _, key_valid = encoder.embed(histories([8, 6, 4, 2] * 8))
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


def test_memory_reset_where_zeroes_exactly_the_done_rows() -> None:
    encoder = build("gtrxl-memory")
    memory = full_memory(encoder, 5)
    before = [layer.clone() for layer in memory.layers]
    done = torch.tensor([True, False, True, False, False])
    assert memory.reset_where(done) is memory
    for old, new in zip(before, memory.layers, strict=True):
        assert torch.all(new[done] == 0.0)
        torch.testing.assert_close(new[~done], old[~done], atol=0, rtol=0)
    assert torch.equal(memory.valid, ~done[:, None].expand(5, 4))
    with pytest.raises(ValueError, match="one done flag per episode"):
        memory.reset_where(torch.tensor([True, False]))


def test_memory_is_used_and_pushed() -> None:
    encoder = build("gtrxl-memory")
    assert isinstance(encoder, GTrXLEncoder)
    batch = histories([HISTORY] * 3 + [5] * 3)
    with torch.no_grad():
        fresh_out, fresh_next = encoder(batch, encoder.initial_memory(6))
        full = full_memory(encoder, 6)
        full_out, full_next = encoder(batch, full)
        # Content in memory changes the output...
        assert (full_out - fresh_out).abs().amax(dim=1).min() > 1e-3
        # ...but only in valid slots: an invalid slot's content is masked out.
        hidden = Memory(full.layers, torch.zeros_like(full.valid))
        hidden_out, _ = encoder(batch, hidden)
        torch.testing.assert_close(hidden_out, fresh_out, atol=1e-5, rtol=0)
        # Ending an episode empties its memory: that row reads as a fresh start.
        reset_out, _ = encoder(batch, full_memory(encoder, 6).reset_where(torch.arange(6) < 2))
        torch.testing.assert_close(reset_out[:2], fresh_out[:2], atol=1e-5, rtol=0)
        assert (reset_out[2:] - fresh_out[2:]).abs().amax(dim=1).min() > 1e-3
        block_input, _, _ = encoder.embed(batch)

    for memory in (fresh_next, full_next):
        assert memory is not None
        assert len(memory.layers) == encoder.layers
        assert all(layer.shape == (6, 4, encoder.d_model) for layer in memory.layers)
        assert memory.valid.shape == (6, 4) and memory.valid.dtype == torch.bool
        assert not any(layer.requires_grad for layer in memory.layers)
        # The window's oldest row is pushed; it is a real step only where the window is full.
        assert memory.valid[:, -1].tolist() == [True] * 3 + [False] * 3
        torch.testing.assert_close(memory.layers[0][:, -1], block_input[:, 0])
    assert full_next is not None
    for old, new in zip(full.layers, full_next.layers, strict=True):
        torch.testing.assert_close(new[:, :-1], old[:, 1:], atol=0, rtol=0)


def test_a_streamed_memory_carries_what_has_left_the_window() -> None:
    """The exported graph's Transformer-XL memory (docs/deploy.md) is what lets a policy read
    beyond its window. Two episodes that differ in their first step alone, streamed one step
    per call: once that step has left the window, the graph tells them apart only where its
    memory is fed back from call to call, not where every call starts empty (as the
    learners call their encoders)."""
    from alignrl.agents.agent import Agent, MemberSpec
    from alignrl.deploy.graph import PolicyGraph

    torch.manual_seed(0)
    options = {"d_model": 8, "heads": 2, "layers": 2, "memory_length": 4}
    hyperparameters = {"encoder": "gtrxl", "encoder_kwargs": options, "hidden": [8]}
    spec = MemberSpec("streamer", "aligner", "sac", (HISTORY, FEATURES), 2, 1, hyperparameters)
    graph = PolicyGraph(Agent(spec), [1.0])
    steps = HISTORY + 3
    first = histories([HISTORY], seed=3)[0]
    episode = torch.cat([first, histories([steps - HISTORY], seed=4)[0, HISTORY - steps :]])
    other = episode.clone()
    other[0, 1:] = -other[0, 1:]  # the first step only
    episodes = torch.stack([episode, other])  #                                   (2, steps, F)
    empty = [torch.from_numpy(value) for value in graph.empty_memory(2).values()]
    memory = empty
    with torch.no_grad():
        for step in range(steps):
            window = torch.zeros(2, HISTORY, FEATURES)  #                 right-aligned, padded
            recent = episodes[:, max(0, step - HISTORY + 1) : step + 1]
            window[:, HISTORY - recent.shape[1] :] = recent
            streamed, _, *memory = graph(window, *memory)
            alone, _ = graph(window, *empty)[:2]
            if step == 0:  # nothing in memory yet: the same as an empty one
                torch.testing.assert_close(streamed, alone, rtol=0, atol=1e-6)
            if step >= HISTORY:  # the first step has left: both windows are the same
                assert torch.equal(window[0], window[1])
                torch.testing.assert_close(alone[0], alone[1], rtol=0, atol=1e-6)
                assert (streamed[0] - streamed[1]).abs().max() > 1e-4
    assert memory[-1].sum(dim=1).tolist() == [4.0, 4.0]  # every slot now holds a real step


def test_memory_zeros_and_detach() -> None:
    memory = Memory.zeros(batch=3, layers=2, memory_length=5, d_model=8)
    assert [layer.shape for layer in memory.layers] == [(3, 5, 8)] * 2
    assert memory.length == 5 and not memory.valid.any()
    tracked = Memory([layer.requires_grad_() * 2 for layer in memory.layers], memory.valid)
    assert all(not layer.requires_grad for layer in tracked.detach().layers)


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
    with pytest.raises(ValueError, match=r"'mlp' has no option 'memory_length'.*hidden"):
        make_encoder("mlp", HISTORY, FEATURES, memory_length=2)
    with pytest.raises(ValueError, match="divisible by heads"):
        make_encoder("gtrxl", HISTORY, FEATURES, d_model=30, heads=4)
    assert isinstance(make_encoder("gru", HISTORY, FEATURES, hidden=16), ENCODERS["gru"])


def test_forward_rejects_wrong_input() -> None:
    mlp = build("mlp")
    with pytest.raises(ValueError, match=r"\(batch, rows, 7\)"):
        mlp(torch.zeros(HISTORY, FEATURES))
    with pytest.raises(ValueError, match="exactly 8 rows"):
        mlp(torch.zeros(2, 5, FEATURES))
    with pytest.raises(ValueError, match="keeps no memory"):
        build("gru")(histories([8]), Memory.zeros(1, 1, 2, 4))
    with pytest.raises(ValueError, match="initial_memory"):
        build("gtrxl-memory")(histories([8]), Memory.zeros(1, 1, 2, 4))


def test_all_padding_history_stays_finite() -> None:
    """A zero observation (no valid row at all) must not make the attention softmax NaN."""
    for case in ("gtrxl", "gtrxl-memory", "gru"):
        encoded, _ = build(case)(torch.zeros(2, HISTORY, FEATURES))
        assert torch.isfinite(encoded).all(), case


@pytest.mark.parametrize("case", list(CASES))
def test_forward_on_cuda_matches_cpu(case: str) -> None:
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    encoder = build(case)
    batch = histories([8, 5, 1, 3] * 8, padding="garbage")
    memory = full_memory(encoder, 32) if encoder.keeps_memory else None
    expected, expected_memory = encoder(batch, memory)
    encoder.to("cuda")
    encoded, next_memory = encoder(batch.cuda(), None if memory is None else memory.to("cuda"))
    encoded.square().sum().backward()
    assert encoded.device.type == "cuda"
    torch.testing.assert_close(encoded.cpu(), expected, atol=1e-4, rtol=1e-4)
    assert all(p.grad is not None and p.grad.is_cuda for p in encoder.parameters())
    if expected_memory is not None:
        assert next_memory is not None and next_memory.valid.is_cuda
        torch.testing.assert_close(next_memory.layers[-1].cpu(), expected_memory.layers[-1])
