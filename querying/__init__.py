"""Text -> relevancy -> masks and 3D selections; image metrics. Works on tensors and embeddings only."""
