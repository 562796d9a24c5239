"""Datasets: SynthCity generator, place sets, segmentation sets, datamodules."""
