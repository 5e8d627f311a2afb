"""radarseg: pipelines."""
