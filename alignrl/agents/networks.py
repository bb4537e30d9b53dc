"""History encoders: networks that turn an aligner's observation history into one feature vector.

The input is the history of alignrl/envs/core.py: float32 (batch, history, features), rows
oldest first, zero-padded at the front, column 0 the validity mask (1 = a real step, 0 =
padding). Every encoder returns (batch, output_dim) features and, where it keeps a memory of
past windows, the updated `Memory`. Encoders are chosen by name (`ENCODERS`, `make_encoder`):

* ``mlp``   the flattened history through an MLP; padding is just more input;
* ``gru``   a GRU over the valid rows, its state after the newest row;
* ``gtrxl`` the Gated Transformer-XL of Parisotto et al. 2019, the newest row's embedding.

GRU and GTrXL ignore padding exactly: a history whose last k rows are valid gives the output
of those k rows alone (up to float rounding), whatever the padding rows hold.
"""

from __future__ import annotations

import inspect
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = [
    "ENCODERS",
    "GRUEncoder",
    "GTrXLEncoder",
    "HistoryEncoder",
    "MLPEncoder",
    "Memory",
    "make_encoder",
    "mlp",
    "valid_rows",
]

VALID_COLUMN = 0  # alignrl/envs/core.py: 1.0 in a recorded row, 0.0 in a padding row
POSITION_INIT_STD = 0.02  # learned position embeddings start small beside the row projection


def valid_rows(history: Tensor) -> Tensor:
    """Which rows of a (B, H, F) history are real steps: (B, H) bool."""
    return history[..., VALID_COLUMN] > 0.5


def _blank_padding(history: Tensor, valid: Tensor) -> Tensor:
    # where, not multiply: 0 * NaN is NaN, and garbage in a padding row must not leak through.
    return torch.where(valid[..., None], history, torch.zeros_like(history))  #            (B, H, F)


def _positive_int(owner: str, name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{owner}: {name} must be a positive integer, got {value!r}")
    return value


# --- the interface ------------------------------------------------------------------------


class HistoryEncoder(nn.Module):
    """(B, H, F) history [+ Memory] -> ((B, output_dim) features, Memory or None).

    Shared bookkeeping only: the sizes and the checks of what forward() is given. Encoders
    without a memory return None for it and refuse one passed in.
    """

    output_dim: int
    keeps_memory: bool = False

    def __init__(self, history: int, features: int) -> None:
        super().__init__()
        name = type(self).__name__
        self.history_length = _positive_int(name, "history", history)
        self.n_features = _positive_int(name, "features", features)

    def initial_memory(self, batch: int, device: torch.device | str | None = None) -> Memory | None:
        """The memory to start episodes with; None for encoders that keep none."""
        return None

    def _check(self, history: Tensor, memory: Memory | None, exact_length: bool) -> None:
        name = type(self).__name__
        if history.ndim != 3 or history.shape[-1] != self.n_features:
            raise ValueError(
                f"{name} expects a history of shape (batch, rows, {self.n_features}), got "
                f"{tuple(history.shape)}; add a batch dimension for a single observation"
            )
        rows = history.shape[1]
        if exact_length and rows != self.history_length:
            raise ValueError(f"{name} needs exactly {self.history_length} rows, got {rows}")
        if not 1 <= rows <= self.history_length:
            raise ValueError(f"{name} takes 1 to {self.history_length} rows, got {rows}")
        if memory is not None and not self.keeps_memory:
            raise ValueError(f"{name} keeps no memory; call it with memory=None")


# --- MLP ----------------------------------------------------------------------------------


class MLPEncoder(HistoryEncoder):
    """The whole history flattened, then Linear (+ LayerNorm) + ReLU per hidden layer."""

    def __init__(
        self,
        history: int,
        features: int,
        hidden: Sequence[int] = (256, 256),
        layer_norm: bool = False,
    ) -> None:
        super().__init__(history, features)
        widths = [_positive_int("MLPEncoder", "hidden width", w) for w in hidden]
        if not widths:
            raise ValueError("MLPEncoder: hidden needs at least one layer width, e.g. (256, 256)")
        layers: list[nn.Module] = []
        width_in = history * features
        for width in widths:
            layers.append(nn.Linear(width_in, width))
            if layer_norm:
                layers.append(nn.LayerNorm(width))
            layers.append(nn.ReLU())
            width_in = width
        self.net = nn.Sequential(*layers)
        self.output_dim = widths[-1]

    def forward(self, history: Tensor, memory: Memory | None = None) -> tuple[Tensor, None]:
        self._check(history, memory, exact_length=True)
        return self.net(history.flatten(1)), None  #                     (B, H*F) -> (B, hidden[-1])


# --- GRU ----------------------------------------------------------------------------------


class GRUEncoder(HistoryEncoder):
    """A single-layer GRU run over the rows, oldest first; the output is its state after the
    newest row. Padding rows are skipped (the state passes through them unchanged), so the
    output is that of the valid rows alone; a history with no valid row gives zeros."""

    def __init__(self, history: int, features: int, hidden: int = 64) -> None:
        super().__init__(history, features)
        self.hidden = _positive_int("GRUEncoder", "hidden", hidden)
        self.cell = nn.GRUCell(features, hidden)
        self.output_dim = hidden

    def forward(self, history: Tensor, memory: Memory | None = None) -> tuple[Tensor, None]:
        self._check(history, memory, exact_length=False)
        valid = valid_rows(history)  #                                                        (B, H)
        rows = _blank_padding(history, valid)  #                                           (B, H, F)
        state = rows.new_zeros(rows.shape[0], self.hidden)  #                            (B, hidden)
        for step in range(rows.shape[1]):
            updated = self.cell(rows[:, step], state)  #                                 (B, hidden)
            # A GRU step on a zero row still moves the state (its biases): skip, don't feed.
            state = torch.where(valid[:, step, None], updated, state)  #                 (B, hidden)
        return state, None


# --- GTrXL --------------------------------------------------------------------------------


@dataclass
class Memory:
    """Transformer-XL memory of a GTrXL encoder: for each block, the block inputs of the last
    `length` rows that have left the history window, oldest first.

    Each call of the encoder pushes the window's oldest row (it leaves the window on the next
    step), so memory + window is one contiguous stretch of the episode when the encoder is
    called once per environment step. `valid` marks slots holding a real step; empty slots
    (episode start, padding rows) are masked out of attention like padding rows.
    """

    layers: list[Tensor]  # one per block                                            (B, M, d_model)
    valid: Tensor  # which slots hold a real step                                        (B, M) bool

    @classmethod
    def zeros(
        cls,
        batch: int,
        layers: int,
        memory_length: int,
        d_model: int,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> Memory:
        """An empty memory: all slots zero and invalid."""
        return cls(
            layers=[
                torch.zeros(batch, memory_length, d_model, device=device, dtype=dtype)
                for _ in range(layers)
            ],
            valid=torch.zeros(batch, memory_length, dtype=torch.bool, device=device),
        )

    @property
    def length(self) -> int:
        return self.valid.shape[1]

    @property
    def batch_size(self) -> int:
        return self.valid.shape[0]

    def detach(self) -> Memory:
        return Memory([layer.detach() for layer in self.layers], self.valid)

    def to(self, device: torch.device | str) -> Memory:
        return Memory([layer.to(device) for layer in self.layers], self.valid.to(device))

    def reset_where(self, done: Tensor) -> Memory:
        """Empty the memory of the episodes that have ended (done: (B,) bool); returns self.

        Fields are replaced, not written in place, so tensors already handed out (and any
        autograd graph through them) are untouched."""
        done = torch.as_tensor(done, device=self.valid.device).to(torch.bool)
        if done.shape != (self.batch_size,):
            raise ValueError(
                f"reset_where needs one done flag per episode, shape ({self.batch_size},), "
                f"got {tuple(done.shape)}"
            )
        self.layers = [layer.masked_fill(done[:, None, None], 0.0) for layer in self.layers]
        self.valid = self.valid & ~done[:, None]  #                                           (B, M)
        return self

    def push(self, rows: Sequence[Tensor], valid: Tensor) -> Memory:
        """A new memory: drop the oldest slot, append one row per block ((B, d_model) each,
        with validity (B,) bool)."""
        layers = [
            torch.cat([layer[:, 1:], row[:, None]], dim=1)  #                        (B, M, d_model)
            for layer, row in zip(self.layers, rows, strict=True)
        ]
        return Memory(layers, torch.cat([self.valid[:, 1:], valid[:, None]], dim=1))


class GRUGate(nn.Module):
    """The GRU-type gating layer that replaces each residual connection in GTrXL
    (Parisotto et al. 2019, "Stabilizing Transformers for Reinforcement Learning"):

        r = sigmoid(W_r y + U_r x)
        z = sigmoid(W_z y + U_z x - b_g)
        h = tanh(W_g y + U_g (r * x))
        g(x, y) = (1 - z) * x + z * h

    x is the residual stream, y the sub-layer output. With b_g > 0 the update gate z starts
    near 0, so the block starts near the identity (the paper's b_g = 2 gives z ~ 0.12).
    """

    def __init__(self, d_model: int, gate_bias: float) -> None:
        super().__init__()
        self.from_sublayer = nn.Linear(d_model, 3 * d_model, bias=False)  # W_r, W_z, W_g
        self.from_stream = nn.Linear(d_model, 2 * d_model, bias=False)  # U_r, U_z
        self.from_reset_stream = nn.Linear(d_model, d_model, bias=False)  # U_g
        self.update_bias = nn.Parameter(torch.full((d_model,), float(gate_bias)))  # b_g

    def forward(self, stream: Tensor, sublayer: Tensor) -> Tensor:
        w_r, w_z, w_g = self.from_sublayer(sublayer).chunk(3, dim=-1)  #              (B, n, d) each
        u_r, u_z = self.from_stream(stream).chunk(2, dim=-1)  #                       (B, n, d) each
        reset = torch.sigmoid(w_r + u_r)
        update = torch.sigmoid(w_z + u_z - self.update_bias)
        candidate = torch.tanh(w_g + self.from_reset_stream(reset * stream))
        return torch.lerp(stream, candidate, update)  # (1 - z) x + z h                    (B, n, d)


class GTrXLBlock(nn.Module):
    """One GTrXL layer: LayerNorm at the input of each sub-layer ("identity map reordering"),
    multi-head attention over [memory, window], then a position-wise feed-forward network,
    each joined to the stream by a GRU gate after a ReLU (Parisotto et al. 2019)."""

    def __init__(self, d_model: int, heads: int, feedforward: int, gate_bias: float) -> None:
        super().__init__()
        self.heads = heads
        self.head_dim = d_model // heads
        self.attention_norm = nn.LayerNorm(d_model)
        self.query = nn.Linear(d_model, d_model)
        self.key_value = nn.Linear(d_model, 2 * d_model)
        self.attention_out = nn.Linear(d_model, d_model)
        self.attention_gate = GRUGate(d_model, gate_bias)
        self.feedforward_norm = nn.LayerNorm(d_model)
        self.feedforward = nn.Sequential(
            nn.Linear(d_model, feedforward), nn.ReLU(), nn.Linear(feedforward, d_model)
        )
        self.feedforward_gate = GRUGate(d_model, gate_bias)

    def forward(
        self,
        stream: Tensor,
        key_valid: Tensor,
        memory: Tensor | None = None,
        newest_only: bool = False,
    ) -> Tensor:
        """stream (B, n, d), key_valid (B, M + n) bool, memory (B, M, d) or None -> (B, n, d),
        or (B, 1, d) for the newest row alone: all the last block needs to compute."""
        queries = 1 if newest_only else stream.shape[1]
        # The paper normalises memory and window together: LayerNorm([StopGrad(M), E]).
        context = stream if memory is None else torch.cat([memory, stream], dim=1)
        context = self.attention_norm(context)  #                                        (B, M+n, d)
        stream = stream[:, -queries:]  #                                                   (B, q, d)
        attended = self.attend(context[:, -queries:], context, key_valid)  #               (B, q, d)
        stream = self.attention_gate(stream, F.relu(attended))  #                          (B, q, d)
        expanded = self.feedforward(self.feedforward_norm(stream))  #                      (B, q, d)
        return self.feedforward_gate(stream, F.relu(expanded))  #                          (B, q, d)

    def attend(self, queries: Tensor, context: Tensor, key_valid: Tensor) -> Tensor:
        """Multi-head attention of the query rows over all valid keys.

        The key mask of one sample, memory_length M = 3, history H = 5, 2 steps so far
        (so the memory is still empty), is the same for every query row:

                       memory (oldest -> newest)    window (oldest -> newest)
            key:         m0    m1    m2              r0    r1    r2    r3    r4
            valid:        .     .     .               .     .     .     X     X
                                                                        (X = may attend)

        Padding queries (r0..r2) attend to the valid keys too; their outputs are never read
        as keys, and the encoder output is the newest row, so they change nothing.
        """
        batch, rows, d_model = queries.shape
        keys_total = context.shape[1]
        query = self.query(queries).view(batch, rows, self.heads, self.head_dim)
        query = query.transpose(1, 2)  #                                               (B, h, q, dh)
        key_value = self.key_value(context).view(batch, keys_total, 2, self.heads, self.head_dim)
        key, value = key_value.permute(2, 0, 3, 1, 4)  #                             (B, h, M+n, dh)
        # The boolean mask puts -inf on the scores of masked keys: exactly zero weight after
        # the softmax. A query with every key masked softmaxes -inf against -inf: NaN in older
        # PyTorch and some kernels, silently zeros in others. None has one here: the encoder
        # always marks the newest row's key valid.
        mixed = F.scaled_dot_product_attention(
            query, key, value, attn_mask=key_valid[:, None, None, :]
        )  #                                                                           (B, h, q, dh)
        mixed = mixed.transpose(1, 2).reshape(batch, rows, d_model)  #                     (B, q, d)
        return self.attention_out(mixed)  #                                                (B, q, d)


class GTrXLEncoder(HistoryEncoder):
    """Gated Transformer-XL (Parisotto et al. 2019) over the history rows.

    Rows are projected to d_model and given a learned position embedding indexed by age
    (the newest row always has the last one, as histories are right-aligned), then pass
    through `layers` GTrXL blocks; the output is the final LayerNorm of the newest row.

    With memory_length > 0 each block also attends over a `Memory` of the block inputs of
    rows that have already left the window (plus a learned embedding per memory slot), and
    forward() returns the updated memory. Call it with full windows, once per environment
    step, and `reset_where(done)` the memory when episodes end; memory=None starts empty.
    """

    def __init__(
        self,
        history: int,
        features: int,
        d_model: int = 32,
        heads: int = 2,
        layers: int = 1,
        memory_length: int = 0,
        gate_bias: float = 2.0,
        feedforward: int | None = None,
    ) -> None:
        super().__init__(history, features)
        name = "GTrXLEncoder"
        self.d_model = _positive_int(name, "d_model", d_model)
        self.heads = _positive_int(name, "heads", heads)
        self.layers = _positive_int(name, "layers", layers)
        if d_model % heads:
            raise ValueError(f"{name}: d_model ({d_model}) must be divisible by heads ({heads})")
        if isinstance(memory_length, bool) or not isinstance(memory_length, int):
            raise ValueError(f"{name}: memory_length must be an integer, got {memory_length!r}")
        if memory_length < 0:
            raise ValueError(f"{name}: memory_length must be 0 (none) or more, got {memory_length}")
        self.memory_length = memory_length
        self.keeps_memory = memory_length > 0
        width = 4 * d_model if feedforward is None else feedforward
        width = _positive_int(name, "feedforward", width)
        self.input_projection = nn.Linear(features, d_model)
        # Oldest first, like the rows: a window of n rows uses the last n embeddings.
        self.position = nn.Parameter(POSITION_INIT_STD * torch.randn(history, d_model))
        self.memory_position = (
            nn.Parameter(POSITION_INIT_STD * torch.randn(memory_length, d_model))
            if memory_length
            else None
        )
        self.blocks = nn.ModuleList(
            GTrXLBlock(d_model, heads, width, gate_bias) for _ in range(layers)
        )
        self.output_norm = nn.LayerNorm(d_model)
        self.output_dim = d_model

    def initial_memory(self, batch: int, device: torch.device | str | None = None) -> Memory | None:
        if not self.memory_length:
            return None
        return Memory.zeros(
            batch,
            self.layers,
            self.memory_length,
            self.d_model,
            device=self.position.device if device is None else device,
            dtype=self.position.dtype,
        )

    def embed(self, history: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The first block's input (B, n, d), the rows' validity (B, n) and the window's key
        mask (B, n): the validity with the newest row always on."""
        valid = valid_rows(history)  #                                                        (B, n)
        rows = history.shape[1]
        stream = self.input_projection(_blank_padding(history, valid))  #                  (B, n, d)
        stream = stream + self.position[-rows:]  #                                         (B, n, d)
        # Guard: a query whose keys are all masked softmaxes -inf against -inf (NaN on older
        # PyTorch). The newest row is real in every env observation; forcing its key valid
        # keeps even an all-padding history (a zero observation) finite on every version.
        newest = torch.zeros_like(valid)
        newest[:, -1] = True
        return stream, valid, valid | newest

    def forward(
        self, history: Tensor, memory: Memory | None = None
    ) -> tuple[Tensor, Memory | None]:
        self._check(history, memory, exact_length=self.memory_length > 0)
        batch = history.shape[0]
        if self.memory_length and memory is None:
            memory = self.initial_memory(batch, device=history.device)
        if memory is not None:
            self._check_memory(memory, batch)
        stream, row_valid, key_valid = self.embed(history)
        if memory is not None:
            key_valid = torch.cat([memory.valid, key_valid], dim=1)  #                      (B, M+n)
        block_inputs = []
        for index, block in enumerate(self.blocks):
            block_inputs.append(stream)
            past = None
            if memory is not None:
                # StopGrad(M) of the paper: no gradient into past steps' activations; the
                # learned slot embedding is added after it, so it still trains.
                past = memory.layers[index].detach() + self.memory_position  #             (B, M, d)
            last = index == len(self.blocks) - 1
            stream = block(stream, key_valid, past, newest_only=last)  #              (B, n or 1, d)
        encoded = self.output_norm(stream[:, -1])  # the newest row                           (B, d)
        if memory is None:
            return encoded, None
        # The oldest row leaves the window next step; it lives on in the memory. Stored
        # without gradient: the paper's StopGrad(M), and no graph kept alive across steps.
        leaving = [inputs[:, 0].detach() for inputs in block_inputs]  #                  (B, d) each
        return encoded, memory.push(leaving, row_valid[:, 0])

    def _check_memory(self, memory: Memory, batch: int) -> None:
        expected = (batch, self.memory_length, self.d_model)
        shapes = [tuple(layer.shape) for layer in memory.layers]
        if len(shapes) != self.layers or any(shape != expected for shape in shapes):
            raise ValueError(
                f"GTrXLEncoder: memory must hold {self.layers} tensors of shape {expected}, "
                f"got {shapes}; start episodes with encoder.initial_memory(batch)"
            )
        if tuple(memory.valid.shape) != expected[:2]:
            raise ValueError(
                f"GTrXLEncoder: memory.valid must have shape {expected[:2]}, "
                f"got {tuple(memory.valid.shape)}"
            )


# --- registry -----------------------------------------------------------------------------

_POSITIONAL = ("history", "features")  # make_encoder's own arguments, not encoder options

ENCODERS: dict[str, type[HistoryEncoder]] = {
    "mlp": MLPEncoder,
    "gru": GRUEncoder,
    "gtrxl": GTrXLEncoder,
}


def mlp(inputs: int, hidden: Sequence[int], outputs: int) -> nn.Sequential:
    """Linear + ReLU per hidden width, then a linear output layer: the learners' heads."""
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [nn.Linear(inputs, width), nn.ReLU()]
        inputs = width
    layers.append(nn.Linear(inputs, outputs))
    return nn.Sequential(*layers)


def make_encoder(name: str, history: int, features: int, **kwargs: Any) -> HistoryEncoder:
    """The encoder registered as `name`, for histories of `history` rows of `features`
    columns, built with its keyword options `kwargs`."""
    if name not in ENCODERS:
        raise ValueError(
            f"unknown history encoder {name!r}; known encoders: {', '.join(sorted(ENCODERS))}"
        )
    encoder_class = ENCODERS[name]
    options = [p for p in inspect.signature(encoder_class).parameters if p not in _POSITIONAL]
    unknown = sorted(set(kwargs) - set(options))
    if unknown:
        raise ValueError(
            f"history encoder {name!r} has no option {', '.join(map(repr, unknown))}; "
            f"its options: {', '.join(options)}"
        )
    return encoder_class(history, features, **kwargs)
