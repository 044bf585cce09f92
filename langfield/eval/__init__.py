"""Evaluation: novel-view image and query scores, geometry, the ablation and the benchmark."""
