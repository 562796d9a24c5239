"""Datasets and readers: SynthCity, place sets and benchmark ground truth, segmentation sets, images."""
