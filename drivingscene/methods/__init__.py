"""Reconstruction methods: frame pair -> Reconstruction (the oracle, the feed-forward model, ...)."""
