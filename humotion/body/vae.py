"""The variational autoencoder of the body model's shape and expression spaces.

Encoder and decoder are MLPs with parametric ReLUs (PReLU). The encoder gives the mean and log
variance of a diagonal Gaussian; training samples it with the reparameterisation trick under an
N(0, I) prior (KL term). The decoder's last layer maps a `basis`-wide hidden layer linearly to the
outputs: its weight can be started from principal components of the training data
(:meth:`VAE.init_output_basis`), so a fresh decoder already spans the data's main directions.

    vae = VAE(inputs=3 * P, outputs=3 * V, latent=16, hidden=256, basis=64)
    mu, logvar = vae.encode(x)                 # x (B, inputs)
    z = vae.sample_posterior(mu, logvar)       # (B, latent)
    y = vae.decode(z)                          # (B, outputs)
    kl = kl_divergence(mu, logvar)             # (B,)
"""

from __future__ import annotations

import torch
from torch import nn


def prelu_mlp(sizes: list[int]) -> nn.Sequential:
    """Linear layers between the given sizes, each followed by a PReLU."""
    layers: list[nn.Module] = []
    for a, b in zip(sizes[:-1], sizes[1:]):
        layers += [nn.Linear(a, b), nn.PReLU(b)]
    return nn.Sequential(*layers)


def kl_divergence(mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """KL(N(mu, exp(logvar)) || N(0, I)) per row: (B, D) -> (B,) nats."""
    return 0.5 * (mu.square() + logvar.exp() - 1.0 - logvar).sum(-1)


class VAE(nn.Module):
    """inputs -> [hidden, hidden] -> (mu, logvar) of `latent`; latent -> [hidden, hidden, basis]
    -> outputs (linear last layer). PReLU everywhere between layers."""

    def __init__(self, inputs: int, outputs: int, latent: int, hidden: int, basis: int):
        super().__init__()
        self.encoder = prelu_mlp([inputs, hidden, hidden])
        self.mu = nn.Linear(hidden, latent)
        self.logvar = nn.Linear(hidden, latent)
        self.decoder = prelu_mlp([latent, hidden, hidden, basis])
        self.output = nn.Linear(basis, outputs)
        with torch.no_grad():
            self.logvar.bias.fill_(-2.0)

    def encode(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, inputs) -> mean, log variance (B, latent)."""
        h = self.encoder(x)
        return self.mu(h), self.logvar(h).clamp(-12.0, 6.0)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """(B, latent) -> (B, outputs)."""
        return self.output(self.decoder(z))

    @staticmethod
    def sample_posterior(mu: torch.Tensor, logvar: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """(B, latent) samples mu + sigma * eps of means mu and log variances logvar (B, latent),
        eps ~ N(0, I) (the reparameterisation trick)."""
        eps = torch.randn(mu.shape, generator=generator, dtype=mu.dtype).to(mu.device)
        return mu + (0.5 * logvar).exp() * eps

    @torch.no_grad()
    def init_output_basis(self, data: torch.Tensor) -> None:
        """Start the last layer from data's principal components: data (N, outputs), already
        centred and scaled as the decoder's targets. Weight columns = the top `basis` components
        times their standard deviations (zero columns when N < basis); bias zero."""
        basis = self.output.in_features
        _, s, vh = torch.linalg.svd(data.double(), full_matrices=False)
        k = min(basis, len(s))
        weight = torch.zeros(self.output.out_features, basis, dtype=torch.float64)
        weight[:, :k] = vh[:k].T * (s[:k] / max(len(data) - 1, 1) ** 0.5)
        self.output.weight.copy_(weight.to(self.output.weight.dtype))
        self.output.bias.zero_()
