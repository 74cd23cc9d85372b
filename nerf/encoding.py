"""Positional encoding: a high-frequency embedding of input coordinates (NeRF, section 5.1).

    gamma(p) = (p, sin(2^0 pi p), cos(2^0 pi p), ..., sin(2^{L-1} pi p), cos(2^{L-1} pi p))

applied to each coordinate of p. For a D-dimensional input and L frequencies the output
has D * (1 + 2L) features (D * 2L without the input itself): the vanilla NeRF uses L = 10
for positions (3 -> 63) and L = 4 for view directions (3 -> 27). Layout of the last axis:
[p (D), sin(2^0 pi p) (D), cos(2^0 pi p) (D), sin(2^1 pi p) (D), ...].
"""

from __future__ import annotations

import math

import torch
from torch import nn


def encoded_size(in_dim: int, n_frequencies: int, include_input: bool = True) -> int:
    """Number of output features of `positional_encoding`: in_dim * (include_input + 2 L)."""
    return in_dim * (int(include_input) + 2 * n_frequencies)


def positional_encoding(p: torch.Tensor, n_frequencies: int, include_input: bool = True) -> torch.Tensor:
    """gamma(p) on the last axis.

    p: [..., D]; n_frequencies: L >= 0. Returns [..., encoded_size(D, L, include_input)] in
    p's dtype. With L = 0 and include_input=True this is the identity.
    """
    if not isinstance(n_frequencies, int) or n_frequencies < 0:
        raise ValueError(f"n_frequencies must be an integer >= 0, got {n_frequencies!r}")
    if p.ndim < 1:
        raise ValueError("p must be [..., D], got a 0-d tensor")
    scales = math.pi * 2.0 ** torch.arange(n_frequencies, dtype=p.dtype, device=p.device)  # [L]
    angles = p[..., None, :] * scales[:, None]  # [..., L, D]
    sin_cos = torch.stack([torch.sin(angles), torch.cos(angles)], dim=-2)  # [..., L, 2, D]
    features = sin_cos.flatten(start_dim=-3)  # [..., 2 L D]
    if include_input:
        features = torch.cat([p, features], dim=-1)
    return features


class PositionalEncoding(nn.Module):
    """`positional_encoding` as a module with its output size: PositionalEncoding(3, 10).out_dim == 63."""

    def __init__(self, in_dim: int, n_frequencies: int, include_input: bool = True):
        super().__init__()
        if not isinstance(in_dim, int) or in_dim < 1:
            raise ValueError(f"in_dim must be an integer >= 1, got {in_dim!r}")
        if not isinstance(n_frequencies, int) or n_frequencies < 0:
            raise ValueError(f"n_frequencies must be an integer >= 0, got {n_frequencies!r}")
        self.in_dim = in_dim
        self.n_frequencies = n_frequencies
        self.include_input = include_input
        self.out_dim = encoded_size(in_dim, n_frequencies, include_input)

    def forward(self, p: torch.Tensor) -> torch.Tensor:
        if p.shape[-1:] != (self.in_dim,):
            raise ValueError(f"expected [..., {self.in_dim}] input, got shape {tuple(p.shape)}")
        return positional_encoding(p, self.n_frequencies, self.include_input)

    def extra_repr(self) -> str:
        return f"in_dim={self.in_dim}, n_frequencies={self.n_frequencies}, out_dim={self.out_dim}"
