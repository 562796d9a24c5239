"""Networks only: backbones, aggregators, mask sources, the teacher and the student, and the folders a
trained teacher or student is saved in."""
