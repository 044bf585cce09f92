"""2D foundation models behind small protocols (segmenter, image-text encoder, depth estimator)."""
