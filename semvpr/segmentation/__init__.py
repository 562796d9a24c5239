"""The segmentation task: training the teacher and the student, pseudo-labels, scoring a segmenter
against ground truth, and the segmentation DataModule."""
