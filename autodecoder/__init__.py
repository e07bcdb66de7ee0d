"""The model: neural stochastic screened Poisson reconstruction (Sellán & Jacobson 2023) and its latent space."""
