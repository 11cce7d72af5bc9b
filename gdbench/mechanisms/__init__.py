"""The paper's two mechanisms, usable without the trainer: structured noise (``noise``) and
variational Gaussians (``variational``)."""
