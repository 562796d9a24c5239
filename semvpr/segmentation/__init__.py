"""The segmentation task: training the teacher (its Lightning module) and the student, pseudo-labels,
scoring a segmenter against ground truth, and the segmentation DataModule."""
