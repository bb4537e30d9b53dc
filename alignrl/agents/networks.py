"""History encoders: networks that turn an aligner's observation history into one feature vector.

The input is the history of alignrl/envs/core.py: float32 (batch, history, features), rows
oldest first, zero-padded at the front, column 0 the validity mask (1 = a real step, 0 =
padding). Every encoder returns (batch, output_dim) features; the history window is its whole
memory, nothing is carried from one call to the next. Encoders are chosen by name (`ENCODERS`,
`make_encoder`):

* ``mlp``   the flattened history through an MLP; padding is just more input;
* ``gru``   a GRU over the valid rows, its state after the newest row;
* ``gtrxl`` the Gated Transformer-XL of Parisotto et al. 2019, the newest row's embedding.

GRU and GTrXL ignore padding exactly: a history whose last k rows are valid gives the output
of those k rows alone (up to float rounding), whatever the padding rows hold.
"""

from __future__ import annotations

import inspect
from collections.abc import Sequence
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
    """(B, H, F) history -> ((B, output_dim) features, None).

    Shared bookkeeping only: the sizes and the checks of what forward() is given. The second
    element of forward()'s result is always None (the learners unpack a pair).
    """

    output_dim: int

    def __init__(self, history: int, features: int) -> None:
        super().__init__()
        name = type(self).__name__
        self.history_length = _positive_int(name, "history", history)
        self.n_features = _positive_int(name, "features", features)

    def _check(self, history: Tensor, exact_length: bool) -> None:
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

    def forward(self, history: Tensor) -> tuple[Tensor, None]:
        self._check(history, exact_length=True)
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

    def forward(self, history: Tensor) -> tuple[Tensor, None]:
        self._check(history, exact_length=False)
        valid = valid_rows(history)  #                                                        (B, H)
        rows = _blank_padding(history, valid)  #                                           (B, H, F)
        state = rows.new_zeros(rows.shape[0], self.hidden)  #                            (B, hidden)
        for step in range(rows.shape[1]):
            updated = self.cell(rows[:, step], state)  #                                 (B, hidden)
            # A GRU step on a zero row still moves the state (its biases): skip, don't feed.
            state = torch.where(valid[:, step, None], updated, state)  #                 (B, hidden)
        return state, None


# --- GTrXL --------------------------------------------------------------------------------


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
    multi-head attention over the window, then a position-wise feed-forward network,
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

    def forward(self, stream: Tensor, key_valid: Tensor, newest_only: bool = False) -> Tensor:
        """stream (B, n, d), key_valid (B, n) bool -> (B, n, d), or (B, 1, d) for the newest
        row alone: all the last block needs to compute."""
        queries = 1 if newest_only else stream.shape[1]
        context = self.attention_norm(stream)  #                                           (B, n, d)
        stream = stream[:, -queries:]  #                                                   (B, q, d)
        attended = self.attend(context[:, -queries:], context, key_valid)  #               (B, q, d)
        stream = self.attention_gate(stream, F.relu(attended))  #                          (B, q, d)
        expanded = self.feedforward(self.feedforward_norm(stream))  #                      (B, q, d)
        return self.feedforward_gate(stream, F.relu(expanded))  #                          (B, q, d)

    def attend(self, queries: Tensor, context: Tensor, key_valid: Tensor) -> Tensor:
        """Multi-head attention of the query rows over all valid keys.

        The key mask of one sample, history H = 5, 2 steps so far, is the same for every
        query row:

                       window (oldest -> newest)
            key:         r0    r1    r2    r3    r4
            valid:        .     .     .     X     X
                                                  (X = may attend)

        Padding queries (r0..r2) attend to the valid keys too; their outputs are never read
        as keys, and the encoder output is the newest row, so they change nothing.
        """
        batch, rows, d_model = queries.shape
        keys_total = context.shape[1]
        query = self.query(queries).view(batch, rows, self.heads, self.head_dim)
        query = query.transpose(1, 2)  #                                               (B, h, q, dh)
        key_value = self.key_value(context).view(batch, keys_total, 2, self.heads, self.head_dim)
        key, value = key_value.permute(2, 0, 3, 1, 4)  #                               (B, h, n, dh)
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
    Attention spans the history window alone: no Transformer-XL memory of earlier windows
    (issue 61: no learner fed one).
    """

    def __init__(
        self,
        history: int,
        features: int,
        d_model: int = 32,
        heads: int = 2,
        layers: int = 1,
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
        width = 4 * d_model if feedforward is None else feedforward
        width = _positive_int(name, "feedforward", width)
        self.input_projection = nn.Linear(features, d_model)
        # Oldest first, like the rows: a window of n rows uses the last n embeddings.
        self.position = nn.Parameter(POSITION_INIT_STD * torch.randn(history, d_model))
        self.blocks = nn.ModuleList(
            GTrXLBlock(d_model, heads, width, gate_bias) for _ in range(layers)
        )
        self.output_norm = nn.LayerNorm(d_model)
        self.output_dim = d_model

    def embed(self, history: Tensor) -> tuple[Tensor, Tensor]:
        """The first block's input (B, n, d) and the window's key mask (B, n): the rows'
        validity with the newest row always on."""
        valid = valid_rows(history)  #                                                        (B, n)
        rows = history.shape[1]
        stream = self.input_projection(_blank_padding(history, valid))  #                  (B, n, d)
        stream = stream + self.position[-rows:]  #                                         (B, n, d)
        # Guard: a query whose keys are all masked softmaxes -inf against -inf (NaN on older
        # PyTorch). The newest row is real in every env observation; forcing its key valid
        # keeps even an all-padding history (a zero observation) finite on every version.
        newest = torch.zeros_like(valid)
        newest[:, -1] = True
        return stream, valid | newest

    def forward(self, history: Tensor) -> tuple[Tensor, None]:
        self._check(history, exact_length=False)
        stream, key_valid = self.embed(history)
        for index, block in enumerate(self.blocks):
            last = index == len(self.blocks) - 1
            stream = block(stream, key_valid, newest_only=last)  #                    (B, n or 1, d)
        return self.output_norm(stream[:, -1]), None  # the newest row                       (B, d)


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
